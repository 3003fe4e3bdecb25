"""The Makefile's bootstrap splits the lock without losing a pin or a hash (requirements/bootstrap.py)."""

from __future__ import annotations

import importlib.util
import json
import os
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


#: what the station, the driver host with each link, the emulated devices and the tools import
NODE_IMPORTS = ("bridge.tools.cli", "bridge.nodes.station", "bridge.nodes.driver_host", "drivers.can",
                "drivers.mavlink", "drivers.udp", "sim_learner.emulator", "sim_learner.mavlink_rover",
                "sim_learner.can_ecu", "sim_learner.experiments", "bridge.tools.demo", "pymavlink.mavutil",
                "MAVProxy.mavproxy")


def test_what_the_nodes_import_was_byte_compiled_by_the_install() -> None:
    """The bootstrap leaves some installed files uncompiled (requirements/bootstrap.py); none that a node imports,
    or every process that imports it, the suite's hundreds, compiles it from its source again (the suite runs with
    ``PYTHONDONTWRITEBYTECODE``). Only for an environment the bootstrap made (its stamp)."""
    if not (Path(sys.prefix) / ".installed").exists():
        pytest.skip("not the Makefile's environment (no .installed stamp)")
    code = ("import importlib, importlib.util, json, os, sys, sysconfig\n"
            f"for name in {NODE_IMPORTS!r}:\n"
            "    importlib.import_module(name)\n"
            "lib = sysconfig.get_paths()['purelib']\n"
            "print(json.dumps(sorted(m.__file__ for m in list(sys.modules.values())\n"
            "    if (getattr(m, '__file__', None) or '').endswith('.py') and m.__file__.startswith(lib)\n"
            "    and not os.path.exists(importlib.util.cache_from_source(m.__file__)))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT,
                         env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.splitlines()[-1]) == []
