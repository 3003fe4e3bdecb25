"""The Makefile's bootstrap splits the lock without losing a pin or a hash (requirements/bootstrap.py)."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LOCK = ROOT / "requirements" / "dev.txt"
_spec = importlib.util.spec_from_file_location("bootstrap", ROOT / "requirements" / "bootstrap.py")
assert _spec is not None and _spec.loader is not None
bootstrap = importlib.util.module_from_spec(_spec)  # requirements/ is not a package
_spec.loader.exec_module(bootstrap)


def _pins(text: str) -> dict[str, list[str]]:
    """name -> its hashes, of a pip-compile lock or a part of one."""
    out: dict[str, list[str]] = {}
    name = ""
    for line in text.splitlines():
        if m := re.match(r"^([A-Za-z0-9_.\-]+)==", line):
            name = m.group(1).lower()
            out[name] = []
        elif h := re.search(r"--hash=(sha256:[0-9a-f]{64})", line):
            out[name].append(h.group(1))
    return out


def test_the_lock_splits_into_its_first_packages_and_the_rest_with_every_hash() -> None:
    text = LOCK.read_text()
    first, rest = bootstrap.split_lock(text, {"numpy", "scipy", "numba", "llvmlite"})
    whole, a, b = _pins(text), _pins(first), _pins(rest)
    assert set(a) == {"numpy", "scipy", "numba", "llvmlite"} and not set(a) & set(b)
    assert {**a, **b} == whole and all(whole.values())
    for part in (first, rest):  # each part is a requirements file pip reads: no line ends in a dangling backslash
        assert not part.rstrip().endswith("\\") and "\\\n\n" not in part


def test_a_first_package_the_lock_does_not_pin_is_refused() -> None:
    with pytest.raises(SystemExit, match="not-a-package not pinned"):
        bootstrap.split_lock(LOCK.read_text(), {"numpy", "not-a-package"})


def test_pip_reads_both_parts(tmp_path: Path) -> None:
    first, rest = bootstrap.split_lock(LOCK.read_text(), {"numpy", "scipy", "numba", "llvmlite"})
    for name, part in (("first.txt", first), ("rest.txt", rest)):
        (tmp_path / name).write_text(part)
        # pip's own parser, offline: every line a requirement with its hashes
        code = ("import sys; from pip._internal.req.req_file import parse_requirements; "
                "from pip._internal.network.session import PipSession; "
                "reqs = list(parse_requirements(sys.argv[1], session=PipSession())); "
                "assert reqs and all(r.options.get('hashes') for r in reqs), len(reqs); print(len(reqs))")
        out = subprocess.run([sys.executable, "-c", code, str(tmp_path / name)], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr[-2000:]
        assert int(out.stdout) == len(_pins(part))
