"""The install split and the locks.

The robot side (the driver host, the vehicle drivers, the wire messages) is the base install: it must run without
the station's heavy packages. And the hashed locks in requirements/ must agree with pyproject.toml's groups.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
ROBOT_LOCK = ROOT / "requirements" / "robot.txt"
DEV_LOCK = ROOT / "requirements" / "dev.txt"
LOCKED_PY = "3.11"  # the Python the locks were compiled for (Makefile LOCKED_PY, lock headers, README)

#: What only the station and the simulations need; the robot side must never import these.
HEAVY = ("scipy", "casadi", "numba", "llvmlite", "matplotlib")
# The driver host imports the wire messages itself; they are not named here so that the test does not depend on
# the wire module's file name.
ROBOT_MODULES = ("bridge.nodes.driver_host", "drivers", "drivers.can", "drivers.mavlink", "drivers.udp")

_BLOCKED_RUN = f"""
import runpy, sys
HEAVY = {HEAVY!r}
tried = []
class Blocker:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in HEAVY:
            tried.append(name)
            raise ImportError(f"{{name}} is not installed on the robot (blocked by tests/repo/test_install.py)")
        return None
sys.meta_path.insert(0, Blocker())
import importlib
for mod in {ROBOT_MODULES!r}:
    importlib.import_module(mod)
sys.argv = ["scmbridge", "driver", "--help"]
try:
    runpy.run_module("bridge.tools.cli", run_name="__main__", alter_sys=True)
except SystemExit as e:
    if e.code not in (0, None):
        raise
loaded = sorted(m for m in sys.modules if m.split(".")[0] in HEAVY)
print("HEAVY-TRIED", tried, "HEAVY-LOADED", loaded)
"""


def test_robot_side_runs_without_station_packages() -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(
        [sys.executable, "-c", _BLOCKED_RUN], cwd=ROOT, env=env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert "usage: scmbridge driver" in out.stdout
    assert "--link {can,mavlink,udp}" in out.stdout
    # Not even a guarded `try: import scipy` on the way: the robot side does not reach for them at all.
    assert "HEAVY-TRIED [] HEAVY-LOADED []" in out.stdout, out.stdout


def _lock_pins(path: Path) -> dict[str, tuple[str, int]]:
    """name -> (pinned version, number of hashes) for every `name==version` entry of a pip-compile lock."""
    pins: dict[str, tuple[str, int]] = {}
    name = None
    for line in path.read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s\\;]+)", line)
        if m:
            name = canonicalize_name(m[1])
            pins[name] = (m[2], 0)
        elif name and line.strip().startswith("--hash=sha256:"):
            pins[name] = (pins[name][0], pins[name][1] + 1)
        elif line and not line.startswith((" ", "#")):
            pytest.fail(f"{path.name}: unexpected line {line!r} (every entry must be name==version with hashes)")
    return pins


def _applies(req: Requirement) -> bool:
    """Does the requirement apply on the locked Python? (The lock is resolved for that Python only.)"""
    env = {"python_version": LOCKED_PY, "python_full_version": f"{LOCKED_PY}.0", "extra": ""}
    return req.marker is None or req.marker.evaluate(env)


def _group(name: str) -> list[Requirement]:
    if name == "base":
        return [Requirement(r) for r in PYPROJECT["project"]["dependencies"]]
    return [Requirement(r) for r in PYPROJECT["project"]["optional-dependencies"][name]]


@pytest.mark.parametrize(
    ("lock", "groups"),
    [(ROBOT_LOCK, ["base"]), (DEV_LOCK, ["base", "station", "sims", "test", "dev"])],
    ids=["robot", "dev"],
)
def test_every_dependency_is_pinned_in_its_lock(lock: Path, groups: list[str]) -> None:
    pins = _lock_pins(lock)
    for group in groups:
        for req in _group(group):
            if not _applies(req):
                continue
            key = canonicalize_name(req.name)
            assert key in pins, f"{req} ([{group}]) is not in {lock.name}: run `make lock`"
            version, hashes = pins[key]
            assert req.specifier.contains(version, prereleases=True), (
                f"{lock.name} pins {req.name}=={version}, pyproject [{group}] asks {req}: run `make lock`"
            )
    for key, (version, hashes) in pins.items():
        assert hashes > 0, f"{lock.name}: {key}=={version} has no hash"
    # Setuptools builds the project itself with --no-build-isolation: it must come from the lock, hashed.
    build_requires = [Requirement(r) for r in PYPROJECT["build-system"]["requires"]]
    for req in build_requires:
        key = canonicalize_name(req.name)
        assert key in pins and req.specifier.contains(pins[key][0]), f"{lock.name}: build requirement {req}"


def test_robot_lock_is_the_dev_lock_restricted() -> None:
    robot, dev = _lock_pins(ROBOT_LOCK), _lock_pins(DEV_LOCK)
    assert {k: v[0] for k, v in robot.items()} == {k: dev[k][0] for k in robot if k in dev}
    assert set(robot) <= set(dev)
    assert not set(robot) & set(HEAVY), "the robot lock must not carry station packages"


def test_extras_nest_and_the_tools_are_pinned() -> None:
    names = {g: {canonicalize_name(r.name) for r in _group(g)} for g in ("station", "sims", "test", "dev")}
    assert names["station"] <= names["sims"] <= names["dev"]
    assert names["test"] <= names["dev"]
    assert {"scipy", "casadi", "numba", "foxglove-sdk", "mcap"} == names["station"]
    assert "matplotlib" in names["sims"] and not names["sims"] & {"pytest", "pip-tools"}
    dev = _lock_pins(DEV_LOCK)
    for tool in ("ruff", "pytest", "hypothesis", "pytest-timeout", "mpmath", "pip-tools", "pip", "setuptools"):
        assert tool in dev, tool


def test_locks_name_the_python_they_were_made_for() -> None:
    for lock in (ROBOT_LOCK, DEV_LOCK):
        head = lock.read_text()[:600]
        assert f"# Locked for CPython {LOCKED_PY} on Linux x86_64" in head
        assert f"autogenerated by pip-compile with Python {LOCKED_PY}" in head
    assert f"LOCKED_PY := {LOCKED_PY}" in (ROOT / "Makefile").read_text()


def test_numpy_cap_matches_numba() -> None:
    """numba pins a numpy range; the base numpy requirement must not allow a numpy the pinned numba refuses."""
    from importlib import metadata

    try:
        numba_reqs = [Requirement(r) for r in metadata.requires("numba") or []]
    except metadata.PackageNotFoundError:
        pytest.skip("numba is not installed (robot-side install)")
    numba_numpy = next(r for r in numba_reqs if canonicalize_name(r.name) == "numpy" and _applies(r))
    ours = next(r for r in _group("base") if r.name == "numpy")
    upper = [s for s in ours.specifier if s.operator in ("<", "<=")]
    assert upper, f"pyproject's numpy has no upper bound; numba asks {numba_numpy.specifier}"
    theirs = [s for s in numba_numpy.specifier if s.operator in ("<", "<=")]
    assert theirs and upper[0].version == theirs[0].version, (ours, numba_numpy)


ROBOT_FILES = ROOT / "requirements" / "robot-files.json"


def _lock_hashes(path: Path) -> dict[str, set[str]]:
    """``{name==version: {sha256, ...}}`` of a pip-compile lock with hashes."""
    out: dict[str, set[str]] = {}
    pin = None
    for line in path.read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9_.\-]+)==([^\s;\\]+)", line)
        if m:
            pin = f"{m.group(1).lower()}=={m.group(2)}"
            out[pin] = set()
        for h in re.findall(r"--hash=sha256:([0-9a-f]{64})", line):
            if pin is not None:
                out[pin].add(h)
    return out


def test_the_robot_lock_installs_on_an_aarch64_robot_computer() -> None:
    """Finding: the lock was for x86_64 only, while many robot computers are aarch64. Each pin of the robot lock has a
    file that installs on CPython 3.11, Linux aarch64 (a pure wheel, a manylinux aarch64 wheel, or an sdist), and the
    lock carries its hash: `pip install --require-hashes -r requirements/robot.txt` works there. Checked offline from
    requirements/robot-files.json, which `make lock` writes from the index (requirements/platforms.py)."""
    from packaging.tags import compatible_tags, cpython_tags
    from packaging.utils import parse_wheel_filename

    platforms = [f"manylinux_2_{m}_aarch64" for m in range(39, 16, -1)] + ["manylinux2014_aarch64", "linux_aarch64"]
    supported = {*cpython_tags((3, 11), platforms=platforms), *compatible_tags((3, 11), "cp311", platforms)}
    files = json.loads(ROBOT_FILES.read_text())
    locked = _lock_hashes(ROBOT_LOCK)
    assert set(files) == set(locked), "requirements/robot-files.json is stale: run `make lock`"
    missing = []
    for pin, hashes in sorted(locked.items()):
        ok = [fn for fn, sha in files[pin].items() if sha in hashes and (
            fn.endswith(".tar.gz") or (fn.endswith(".whl") and set(parse_wheel_filename(fn)[3]) & supported))]
        if not ok:
            missing.append(pin)
    assert not missing, f"no aarch64-installable file with a locked hash for {missing}"


@pytest.mark.timeout(720)  # hang guards only: beside two busy loops the lock's install took over 240 s
def test_a_robot_installs_from_its_lock_and_the_project_offline(tmp_path: Path) -> None:
    """Finding: ROBOT.md's `pip install --no-deps .` fetched setuptools from the network. The robot venv installs the
    lock (from the package index, as the robot's first step does), then the project with no index at all
    (`--no-build-isolation`: the lock's own setuptools builds it), and the driver host runs."""
    import shutil
    import venv

    src = tmp_path / "src"  # a copy: the build leaves build/ and *.egg-info behind
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".venv", ".git", "__pycache__", "*.egg-info", "build",
                                                             ".pytest_cache", "demo_out", ".ruff_cache"))
    env_dir = tmp_path / "robot-venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    # niced and without byte-compiling: the suite's timing-sensitive tests run beside it on the other workers. Not
    # nice 19: beside other work at nice 0 (two busy loops) that starved it past any guard
    pip = ["nice", "-n", "5", str(env_dir / "bin" / "python"), "-m", "pip", "--disable-pip-version-check", "-q"]
    res = subprocess.run([*pip, "install", "--no-compile", "--require-hashes", "-r", str(ROBOT_LOCK)],
                         capture_output=True, text=True, timeout=480)
    assert res.returncode == 0, res.stderr[-2000:]
    res = subprocess.run([*pip, "install", "--no-compile", "--no-index", "--no-deps", "--no-build-isolation", str(src)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    res = subprocess.run([str(env_dir / "bin" / "scmbridge"), "driver", "--help"], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and "usage: scmbridge driver" in res.stdout, res.stderr[-2000:]
