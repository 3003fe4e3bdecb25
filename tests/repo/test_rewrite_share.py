"""The suite's assertion rewriting shared by the xdist workers (tests/rewrite_share.py): a run on two workers with
bytecode writing off leaves a current rewritten copy of every test module and conftest, pytest's assert messages
still explain, and an edited module is rewritten again. Two small pytest runs (no plugins but xdist)."""

from __future__ import annotations

import importlib.util
import marshal
import os
import subprocess
import sys
from pathlib import Path
from types import CodeType

ROOT = Path(__file__).resolve().parents[2]
CONFTEST = "from tests.rewrite_share import share_rewriting\n\n\ndef pytest_configure(config):\n" \
           "    share_rewriting(config)\n"


def _run(where: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "PYTHONPATH": str(ROOT), "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "xdist", "-p", "no:cacheprovider", "-n", "2",
                           str(where)], capture_output=True, text=True, env=env, timeout=120, cwd=where)


def _cached(fn: Path) -> Path | None:
    """The rewritten copy of ``fn`` pytest would load, if there is one for its current source."""
    for pyc in (fn.parent / "__pycache__").glob(fn.stem + ".*-pytest-*.pyc"):
        if pyc.read_bytes()[8:16] == importlib.util.source_hash(fn.read_bytes())[:8]:
            return pyc
    return None


def test_two_workers_leave_a_current_rewritten_copy_of_each_test_module_and_an_edit_is_rewritten_again(
        tmp_path: Path) -> None:
    """Without the sharing, with bytecode writing off, pytest rewrites in memory and caches nothing."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "conftest.py").write_text(CONFTEST)
    files = [tmp_path / f"test_m{i}.py" for i in range(3)] + [tmp_path / "sub" / "test_deep.py"]
    for i, f in enumerate(files):
        f.write_text(f"def test_{i}():\n    x = {i}\n    assert x == {i}\n")
    run = _run(tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr
    assert all(_cached(f) is not None for f in [*files, tmp_path / "conftest.py"])
    files[0].write_text("def test_edited():\n    x = 1\n    assert x + 1 == 3\n")  # now fails
    run = _run(tmp_path)
    assert run.returncode == 1 and "assert (1 + 1) == 3" in run.stdout, run.stdout + run.stderr
    pyc = _cached(files[0])  # the edited module's copy is current again, and holds pytest's rewritten assert
    assert pyc is not None
    test = next(c for c in marshal.loads(pyc.read_bytes()[16:]).co_consts if isinstance(c, CodeType))
    assert test.co_name == "test_edited" and any(n.startswith("@py_assert") for n in test.co_varnames)
