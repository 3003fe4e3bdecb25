# Two entry points for a fresh clone: `make demo` and `make test`.
# Both create .venv with pip when it is missing and install the project (with its test extra) into it.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench install clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/scmbridge demo $(ARGS)

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q $(PYTEST_ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

bench: $(STAMP)
	$(VENV)/bin/scmbridge bench scm
	$(VENV)/bin/scmbridge bench transfer
	$(VENV)/bin/scmbridge bench mpc

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
