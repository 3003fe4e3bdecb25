"""The suite's assertion rewriting done once for all the xdist workers, not once in each (tests/conftest.py calls
:func:`share_rewriting` on each worker before it collects).

pytest rewrites the ``assert`` statements of every test module and conftest it imports (parse, rewrite, compile) and
caches the result in ``__pycache__`` (a hash-checked ``.pyc`` tagged ``-pytest-``) unless bytecode writing is off.
The suite runs with ``PYTHONDONTWRITEBYTECODE`` set (CI, and the shells the suite is developed in), so each worker
rewrote the whole suite at every start: with several workers on two cores a large part of pytest's start-up. Here each
worker writes those cached files itself, from its own part of the list of files onwards (the workers start at
different places, so each file is rewritten about once in all), and skips a file whose cached copy is current (the
source hash in its header matches). pytest then loads the cached copy when it imports the module; it checks the
hash again, so a copy that went stale meanwhile is rewritten as before. Only this cache is written: the processes the
tests start keep ``PYTHONDONTWRITEBYTECODE`` (the Makefile compiles the project's own bytecode once, at install).
This uses pytest's rewriting functions (``_pytest.assertion.rewrite``; pytest is pinned in requirements/dev.txt):
if they change, :func:`share_rewriting` does nothing and pytest rewrites each module as before."""

from __future__ import annotations

import fnmatch
import importlib.util
from pathlib import Path

import pytest


def _files(config: pytest.Config) -> list[Path]:
    """The test modules and conftests under the paths the run collects (its arguments, or ``testpaths``)."""
    patterns = list(config.getini("python_files")) + ["conftest.py"]
    found: set[Path] = set()
    for arg in config.args:
        p = Path(str(arg).split("::", 1)[0])
        p = p if p.is_absolute() else Path(config.invocation_params.dir) / p
        if p.is_file() and p.suffix == ".py":
            found.add(p.resolve())
        elif p.is_dir():
            found.update(f.resolve() for f in p.rglob("*.py")
                         if "__pycache__" not in f.parts and any(fnmatch.fnmatch(f.name, pat) for pat in patterns))
    return sorted(found)


def share_rewriting(config: pytest.Config) -> int:
    """On an xdist worker whose asserts are rewritten: write pytest's cached rewritten copy of each test module and
    conftest of the run that has none current, starting at this worker's own share of the sorted list (worker k of
    n at k/n of it) and going round; how many it wrote. Elsewhere (no xdist, ``--assert=plain``) nothing."""
    worker = getattr(config, "workerinput", None)
    if worker is None or config.getoption("assertmode", "rewrite") != "rewrite":
        return 0
    try:
        from _pytest.assertion import rewrite
        state = config.stash[rewrite.assertstate_key]
        tail, cache_dir_of, rewrite_test = rewrite.PYC_TAIL, rewrite.get_cache_dir, rewrite._rewrite_test
        write_pyc, makedirs = rewrite._write_pyc, rewrite.try_makedirs
    except (ImportError, AttributeError, KeyError):  # pytest's internals changed: it rewrites as it always did
        return 0
    files = _files(config)
    if not files:
        return 0
    index = int(str(worker.get("workerid", "gw0")).lstrip("gw") or 0)
    count = max(1, int(worker.get("workercount", 1)))
    start = len(files) * (index % count) // count
    written = 0
    for fn in files[start:] + files[:start]:
        cache = cache_dir_of(fn)
        pyc = cache / (fn.name[:-3] + tail)
        try:
            source_hash = importlib.util.source_hash(fn.read_bytes())
            with open(pyc, "rb") as f:
                if f.read(16)[8:16] == source_hash[:8]:
                    continue  # current: another worker (or an earlier run) wrote it
        except FileNotFoundError:
            pass
        except OSError:
            continue
        if not makedirs(cache):
            return written  # a read-only tree: pytest rewrites in memory, as it always did
        try:
            source_hash, code = rewrite_test(fn, config)
            written += bool(write_pyc(state, code, source_hash, pyc))
        except Exception:  # a module that does not compile (pytest reports it when it imports it),
            continue  # or pytest's internals changed: pytest rewrites that module itself, as it always did
    return written
