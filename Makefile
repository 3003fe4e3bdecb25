# Two entry points for a fresh clone: `make demo` and `make test`.
# Both create .venv when it is missing and install exactly the lock into it: requirements/dev.txt, pinned with
# hashes (pip --require-hashes; the lock is complete, so each pip is told --no-deps and `pip check` confirms it),
# then the project itself with --no-build-isolation (setuptools comes from the lock, so nothing unpinned or unhashed
# is fetched). `make lock` regenerates the locks from pyproject.toml.
# The locks are for CPython 3.11 on Linux x86_64: the bootstrap refuses any other Python in one line.
LOCKED_PY := 3.11
PYTHON ?= $(shell command -v python$(LOCKED_PY) 2>/dev/null || echo python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
LOCK := requirements/dev.txt
ROBOT_LOCK := requirements/robot.txt

# One line, exit 1, when the interpreter given as $(1) is not CPython $(LOCKED_PY).
check_python = $(1) -c 'import sys; v = "%d.%d" % sys.version_info[:2]; ok = v == "$(LOCKED_PY)" and sys.implementation.name == "cpython"; sys.exit(0 if ok else f"make: $(1) is {sys.implementation.name} {v}; the lock ($(LOCK)) is for CPython $(LOCKED_PY): make PYTHON=path/to/python$(LOCKED_PY) (rm -rf $(VENV) first if it exists)")'

# pip-compile options shared by both locks; see README "Set-up".
PIP_COMPILE := CUSTOM_COMPILE_COMMAND="make lock" $(VENV)/bin/pip-compile --quiet --generate-hashes --allow-unsafe \
	--strip-extras --all-build-deps --no-emit-index-url --no-emit-find-links --no-emit-trusted-host \
	$(if $(UPGRADE),--upgrade,)
LOCK_NOTE := \# Locked for CPython $(LOCKED_PY) on Linux x86_64 (hashes: every file PyPI has for each pinned version).

.PHONY: demo test test-sitl perf lint bench install lock clean cli-doc

$(PY):
	@$(call check_python,$(PYTHON))
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(PY) $(LOCK) pyproject.toml requirements/bootstrap.py
	@$(call check_python,$(PY))
	@# requirements/bootstrap.py: the lock (pip --require-hashes), the project (editable, no build isolation), the
	@# SC kernels compiled into numba's on-disk cache, the MPC's, and the bytecode of the installed packages and of the
	@# project, on both cores: the packages the SC warm-up needs first, then that warm-up beside the rest of the lock
	@# (pip works on one core), then the bytecode beside the MPC's warm-up. Compiled once here, a kernel is loaded by
	@# every process that needs it (a station starting beside others, or a test's, would spend tens of seconds).
	$(PY) requirements/bootstrap.py $(LOCK) --first $(WARMUP_NEEDS) --warm-first '$(WARMUP_SC)' --warm-last '$(WARMUP_MPC)'
	touch $(STAMP)

# The shipped units (deploy/systemd/) run with NUMBA_CACHE_DIR=$(SERVICE_CACHE)/numba and their cache directory
# $(SERVICE_CACHE) (CacheDirectory=scmbridge): numba uses only a cache it may write, so a service never reads the one
# that root's install left next to the sources. Run as root (`sudo make install`, deploy/README.md step 1), install
# fills the services' cache too and gives it to $(SERVICE_USER): a service's first start loads the kernels instead of
# compiling them (tens of seconds). Run again after an update (it only loads what is still current).
SERVICE_CACHE ?= /var/cache/scmbridge
SERVICE_USER ?= scmbridge
WARMUP_SC := from transfer.scm import warmup; warmup()
WARMUP_NEEDS := numpy,scipy,numba,llvmlite
WARMUP_MPC := from transfer.teacher.mpc import MpcConfig, MpcTeacher; MpcTeacher(MpcConfig(curve_margin=0.9))
WARMUP := $(WARMUP_SC); $(WARMUP_MPC)
# The station's MPC compiled (about a minute of a core each): install only, not the bootstrap (the suite's stations
# run it interpreted, SCMBRIDGE_NO_COMPILE=1; a lab's first station builds it in the background)
MPC_WARMUP := from bridge.nodes.sources import warm_kernels; warm_kernels()

install: $(STAMP)
	@if [ "$$(id -u)" = 0 ]; then \
		echo "make install: filling the services' cache $(SERVICE_CACHE) (numba's SC kernels, the MPC's code)"; \
		mkdir -p $(SERVICE_CACHE)/numba && \
		SCMBRIDGE_CACHE_DIR=$(SERVICE_CACHE) NUMBA_CACHE_DIR=$(SERVICE_CACHE)/numba $(PY) -c '$(WARMUP)' && \
		SCMBRIDGE_CACHE_DIR=$(SERVICE_CACHE) NUMBA_CACHE_DIR=$(SERVICE_CACHE)/numba $(PY) -c '$(MPC_WARMUP)' && \
		if id -u $(SERVICE_USER) >/dev/null 2>&1; then chown -R $(SERVICE_USER): $(SERVICE_CACHE); \
		else echo "make install: no user $(SERVICE_USER) yet: systemd gives it $(SERVICE_CACHE) at the first start"; fi; \
	fi

demo: $(STAMP)
	$(VENV)/bin/scmbridge demo $(ARGS)

# Much of the suite waits on real time (stations at 10 Hz, links, deadmen): with four workers two cores stayed about a
# quarter idle, with six they are nearly full: a tenth quicker, for a seventh more CPU (docs/BENCHMARKS.md, "The test
# suite"; on a slower machine that four already fill, TEST_WORKERS=4 may be quicker). The tests that counted what a
# stalled process did in a fixed window now wait on the count, with a deadline. worksteal: xdist first hands each
# worker a contiguous share of the tests, and a worker whose share ends early takes over half of the busiest one's;
# tests/schedule.py starts the long tests first. The suite's time on a fresh clone: docs/BENCHMARKS.md.
TEST_WORKERS ?= 6
# The tests against ArduPilot's Rover SITL are `make test-sitl` (several minutes: each boots its own SITL and the
# generated profiles drive whole missions). Two at a time on a 2-core machine: each is a vehicle, its driver host and
# a station in real time, and three at once starved them (docs/BENCHMARKS.md, "The SITL tests").
SITL_WORKERS ?= 2
test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal -m "not sitl" $(PYTEST_ARGS)

# tests/integration/test_sitl.py, tests/integration/test_demo_sitl.py: the driver host and one transfer run against
# ArduPilot's real Rover firmware in SITL, found at shared/sitl/ardurover beside the repository (or further up) or $$SCMBRIDGE_SITL; here a
# missing binary fails, never skips.
test-sitl: $(STAMP)
	SCMBRIDGE_SITL_REQUIRED=1 $(PY) -m pytest -q -n $(SITL_WORKERS) -m sitl $(PYTEST_ARGS)

# The regression guard (CI runs it after the tests): the quick benchmarks, one JSON line per figure against its
# target; exit 1 if a figure is over 3x its target (bench/perf.py says how, and how a slow machine is allowed for).
perf: $(STAMP)
	$(VENV)/bin/scmbridge bench perf

lint: $(STAMP)
	$(VENV)/bin/ruff check .

# Keeps every pin pyproject.toml still allows; `make lock UPGRADE=1` moves all pins to the newest allowed.
# The robot lock is resolved first and constrains the dev lock, so both pin the same versions where they overlap.
lock: $(STAMP)
	$(PIP_COMPILE) -o $(ROBOT_LOCK) pyproject.toml
	$(PIP_COMPILE) --extra dev -c $(ROBOT_LOCK) -o $(LOCK) pyproject.toml
	sed -i '2i $(LOCK_NOTE)' $(ROBOT_LOCK) $(LOCK)
	$(VENV)/bin/python requirements/platforms.py $(ROBOT_LOCK)

bench: $(STAMP)
	$(VENV)/bin/scmbridge bench scm
	$(VENV)/bin/scmbridge bench transfer
	$(VENV)/bin/scmbridge bench mpc

# docs/CLI.md is generated from the parsers (tests/repo/test_cli.py checks it is current)
cli-doc: $(STAMP)
	$(PY) -c 'from bridge.tools.cli import reference; import sys; sys.stdout.write(reference())' > docs/CLI.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
