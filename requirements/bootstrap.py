"""The Makefile's install into a fresh virtual environment: the lock, the project, the compiled kernels, the bytecode.

    .venv/bin/python requirements/bootstrap.py LOCK --first numpy,scipy,numba,llvmlite \\
        --warm-first 'CODE' --warm-last 'CODE'

Exactly the lock, hash-checked, binary wheels only (``pip --require-hashes --only-binary=:all:``), then the project
itself, editable, with no build isolation (setuptools comes from the lock: nothing unpinned or unhashed is fetched).
The lock is complete (pip-compile resolved it), so each pip is told ``--no-deps`` and ``pip check`` confirms at the end
that every installed package's requirements are met.

What takes the time is done side by side on two cores instead of one after another:

1. the packages named by ``--first`` (those ``--warm-first`` imports), alone;
2. ``--warm-first`` (compiling the SC kernels into numba's on-disk cache: one core's work) beside the rest of the
   lock and the project (pip works on one core);
3. ``--warm-last`` (what needs the rest: the MPC's kernels) beside the bytecode of the installed packages and of the
   project (``compileall -j 0``). Every process the suite or a lab starts then loads that bytecode instead of
   compiling the sources again (none writes it with ``PYTHONDONTWRITEBYTECODE`` set). Not compiled: the packages'
   own test suites and the MAVLink dialects nothing here imports (pymavlink ships one module of megabytes per
   dialect; the project speaks ardupilotmega, and pymavlink's ``mavutil`` imports ``all``, which every process that
   imports ``mavutil`` would otherwise compile from its source again); a file that is not valid Python 3 (a
   package's Python 2 examples) is left as it is, as pip's own compiling leaves it. ``tests/repo/test_bootstrap.py``
   checks that what the nodes import has its bytecode.

Exit status 1, with the step that failed, if a pip, a warm-up or the check fails.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

#: pip's options for the lock: exactly its files, checked against its hashes
PIP_LOCK = ("install", "--quiet", "--no-compile", "--no-deps", "--require-hashes", "--only-binary=:all:")
#: the project's own directories whose bytecode is compiled
PROJECT_DIRS = ("bridge", "transfer", "drivers", "sim_learner", "bench", "tests")
#: installed files not compiled (module docstring)
NOT_COMPILED = r"/tests/|/pymavlink/dialects/v[12]0/(?!(ardupilotmega|all|__init__)\.py)"


def split_lock(text: str, first: set[str]) -> tuple[str, str]:
    """The lock's pins (each with its hashes) of the packages named in ``first``, and the others'."""
    blocks: list[list[str]] = []
    for line in text.splitlines():
        if re.match(r"^[A-Za-z0-9]", line):
            blocks.append([line])
        elif blocks and line.strip().startswith("--hash="):
            blocks[-1].append(line)
    parts: tuple[list[str], list[str]] = ([], [])
    pinned: set[str] = set()
    for block in blocks:
        name = _norm(re.split(r"[=<>!~\[; ]", block[0], maxsplit=1)[0])
        pinned.add(name)
        parts[0 if name in first else 1].append("\n".join(block).rstrip(" \\"))
    missing = first - pinned
    if missing:
        raise SystemExit(f"bootstrap: {', '.join(sorted(missing))} not pinned in the lock")
    return "\n".join(parts[0]) + "\n", "\n".join(parts[1]) + "\n"


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _run(what: str, cmd: list[str]) -> None:
    if subprocess.run(cmd).returncode != 0:
        raise SystemExit(f"bootstrap: {what} failed")


def _wait(what: str, proc: subprocess.Popen) -> None:
    if proc.wait() != 0:
        raise SystemExit(f"bootstrap: {what} failed")


def bootstrap(lock: Path, first: set[str], warm_first: str, warm_last: str) -> None:
    py = sys.executable
    head, rest = split_lock(lock.read_text(), first)
    background: list[subprocess.Popen] = []
    try:
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "first.txt").write_text(head)
            (Path(d) / "rest.txt").write_text(rest)
            _run("pip (the lock's first packages)", [py, "-m", "pip", *PIP_LOCK, "-r", str(Path(d) / "first.txt")])
            warming = subprocess.Popen([py, "-c", warm_first])
            background.append(warming)
            _run("pip (the rest of the lock)", [py, "-m", "pip", *PIP_LOCK, "-r", str(Path(d) / "rest.txt")])
        _run("pip (the project)", [py, "-m", "pip", "install", "--quiet", "--no-compile", "--no-deps",
                                   "--no-build-isolation", "-e", "."])
        _wait("the first warm-up", warming)
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
        background += [subprocess.Popen([py, "-m", "compileall", "-q", "-j", "0", "-x", NOT_COMPILED,
                                          sysconfig.get_paths()["purelib"]], **quiet),
                       subprocess.Popen([py, "-m", "compileall", "-q", "-j", "0", *PROJECT_DIRS], **quiet)]
        _run("the last warm-up", [py, "-c", warm_last])
        for proc in background[1:]:
            proc.wait()  # a file compileall cannot compile is left to be compiled where it is imported
        _run("pip check", [py, "-m", "pip", "check", "--quiet"])
    finally:
        for proc in background:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lock", type=Path)
    ap.add_argument("--first", required=True, help="comma-separated packages installed first (--warm-first's)")
    ap.add_argument("--warm-first", required=True, help="Python run beside the rest of the install")
    ap.add_argument("--warm-last", required=True, help="Python run once everything is installed")
    args = ap.parse_args(argv)
    bootstrap(args.lock, {_norm(n) for n in args.first.split(",") if n}, args.warm_first, args.warm_last)
    return 0


if __name__ == "__main__":
    sys.exit(main())
