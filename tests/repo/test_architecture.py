"""The shape docs/ARCHITECTURE.md promises, checked from the code's own imports (every import statement, also the
ones inside functions): packages in layers that import only downwards, no cycle between modules, a pure method, a
leaf wire schema, a station that knows no simulator, benchmarks outside the product, and docstrings that cite only
what the repository contains."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path
from typing import get_type_hints

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("transfer", "bridge", "drivers", "sim_learner", "bench")
#: docs/ARCHITECTURE.md section 2: each package's layer; a module imports only from its own layer or below, and
#: the two packages of layer 2 (the links and the learner's emulators) know nothing of each other. ``bench`` (the
#: benchmarks and fuzzers) sits above everything and nothing in the product imports it.
LAYERS = {"transfer": 0, "bridge": 1, "bridge.core": 1, "bridge.teacher": 1, "drivers": 2, "sim_learner": 2,
          "bridge.nodes": 3, "bridge.tools": 4, "bridge.__main__": 4, "bench": 5}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


MODULES = _modules()


def _imports(name: str) -> set[str]:
    """The project modules ``name`` imports (a package import counts as its ``__init__``)."""
    tree = ast.parse(MODULES[name].read_text())
    found: set[str] = set()
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            subs = [f"{node.module}.{a.name}" for a in node.names]
            targets = [t for t in subs if t in MODULES] or [node.module]  # `from pkg import submodule`
        for t in targets:
            if t in MODULES and t != name:
                found.add(t)
    return found


@functools.cache
def _graph() -> dict[str, set[str]]:
    """Every project module's project imports: parsed once, by the first test that needs it (not when the suite is
    collected, which every xdist worker does)."""
    return {m: _imports(m) for m in MODULES}


def _reach(start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for n in _graph()[todo.pop()]:
            if n not in seen:
                seen.add(n)
                todo.append(n)
    return seen


def _package(module: str) -> str:
    """The longest entry of LAYERS that ``module`` belongs to."""
    best = max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len)
    return best


def test_every_module_has_a_layer() -> None:
    assert all(_package(m) for m in MODULES)


def test_packages_import_only_downwards() -> None:
    wrong = []
    for m, deps in _graph().items():
        pm = _package(m)
        for d in deps:
            pd = _package(d)
            if LAYERS[pd] > LAYERS[pm] or (LAYERS[pd] == LAYERS[pm] == 2 and pd != pm):
                wrong.append(f"{m} ({pm}, layer {LAYERS[pm]}) imports {d} ({pd}, layer {LAYERS[pd]})")
    assert not wrong, "imports against the layering:\n" + "\n".join(sorted(wrong))


def test_the_layers_are_what_the_architecture_document_draws() -> None:
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    for pkg in LAYERS:
        if pkg not in ("bridge", "bridge.__main__"):
            assert f"`{pkg.replace('.', '/')}/`" in text or f"`{pkg}`" in text, f"{pkg} is not in docs/ARCHITECTURE.md"


def test_no_module_imports_one_that_imports_it_back() -> None:
    cycles = sorted(m for m in MODULES if m in _reach(m))
    assert not cycles, f"import cycles through: {cycles}"


def test_the_method_is_pure_and_depends_on_no_io_package() -> None:
    for m in MODULES:
        if m.startswith("transfer"):
            assert not [n for n in _graph()[m] if not n.startswith("transfer")], m
            text = MODULES[m].read_text()
            assert not re.search(r"^\s*(import|from)\s+(zenoh|socket|threading|time|can|pymavlink)\b", text, re.M), m


def test_no_module_of_the_method_exceeds_650_lines() -> None:
    """Issue 34: the method's modules stay small enough to read whole (the SC kernels are split by job for it)."""
    long = {m: n for m in MODULES if m.startswith("transfer") and (n := len(MODULES[m].read_text().splitlines())) > 650}
    assert not long, long


def test_the_wire_schema_is_a_leaf() -> None:
    assert _graph()["bridge.core.wire"] == set()


def test_the_station_knows_no_simulator() -> None:
    assert not [m for m in _reach("bridge.nodes.station") if m.startswith("sim_learner")]


def test_the_station_core_runs_without_zenoh_threads_or_module_state() -> None:
    """Many cores (one per robot) run in one process over one session: the core and what it reaches import no
    Zenoh and start no thread."""
    forbidden = re.compile(r"^\s*(import|from)\s+(zenoh|threading)\b", re.M)
    for m in {"bridge.nodes.station_core"} | _reach("bridge.nodes.station_core"):
        assert not forbidden.search(MODULES[m].read_text()), f"the station core reaches {m}, which imports it"


@pytest.mark.parametrize("mod", ["bridge.nodes.engagement", "bridge.nodes.host_status", "bridge.nodes.pose_feed"])
def test_the_driver_hosts_pieces_are_pure(mod: str) -> None:
    """Issue 34: the driver host is the wiring; its engagement, status and pose feed take times and facts as
    arguments: no Zenoh, no threads, no clock, no files or sockets in the module itself."""
    forbidden = re.compile(r"^\s*(import|from)\s+(zenoh|threading|time|socket|os|pathlib|logging)\b", re.M)
    assert not forbidden.search(MODULES[mod].read_text()), f"{mod} imports I/O, a clock or threads"


#: the control path: the station's tick, the driver host's loop and the vehicle links
CONTROL_PATH = ("bridge.nodes.station", "bridge.nodes.station_core", "bridge.nodes.station_fitness",
                "bridge.nodes.station_status", "bridge.nodes.station_saves", "bridge.nodes.pairing",
                "bridge.nodes.mission_control", "bridge.nodes.driver_host", "bridge.nodes.engagement",
                "bridge.nodes.host_status", "bridge.nodes.pose_feed", "bridge.nodes.latch_store", "bridge.core.gate",
                "drivers.base", "drivers.udp", "drivers.can.driver", "drivers.can.axis", "drivers.can.odometry",
                "drivers.mavlink.driver", "drivers.mavlink.client", "drivers.mavlink.state", "transfer.step",
                "transfer.policy", "transfer.store")


def test_no_class_on_the_control_path_has_more_than_15_public_methods() -> None:
    """Issue 34: one job per class. (Properties are not counted: they read state, they do no job.)"""
    big = {}
    for mod in CONTROL_PATH:
        for cls in ast.walk(ast.parse(MODULES[mod].read_text())):
            if isinstance(cls, ast.ClassDef):
                public = [f.name for f in cls.body if isinstance(f, ast.FunctionDef) and not f.name.startswith("_")
                          and not any(getattr(d, "id", getattr(d, "attr", "")) in ("property", "setter")
                                      for d in f.decorator_list)]
                if len(public) > 15:
                    big[f"{mod}.{cls.name}"] = public
    assert not big, big


@pytest.mark.parametrize("mod", ["bridge.nodes.driver_cmd", "bridge.nodes.driver_host", "drivers.can",
                                 "drivers.mavlink", "drivers.udp"])
def test_the_robot_side_needs_no_numerical_stack(mod: str) -> None:
    heavy = re.compile(r"^\s*(import|from)\s+(scipy|casadi|numba|matplotlib)\b", re.M)
    for m in {mod} | _reach(mod):
        if m.startswith("sim_learner"):
            continue  # --emulate hosts the emulated controllers: not needed on a robot
        assert not heavy.search(MODULES[m].read_text()), f"{mod} reaches {m}, which imports the numerical stack"


def test_docs_cite_only_what_the_repository_contains() -> None:
    outside = re.compile(r"DESIGN\.md|SCM_SPEC|SCM_NOTES|\.\./shared")
    for f in [*MODULES.values(), *ROOT.glob("tests/*.py"), *ROOT.glob("*.md"), *ROOT.glob("docs/*.md")]:
        if f.name == "test_architecture.py":
            continue
        assert not outside.search(f.read_text()), f"{f} cites a document outside the repository"
    assert (ROOT / "docs" / "ARCHITECTURE.md").exists()


def test_every_link_is_named_in_one_table() -> None:
    """The links a user can pick (every `--link` option) are the drivers' registry, the driver host's configuration
    has a section for each (its own config struct), and each module names its config and driver."""
    import ast

    import drivers
    from bridge.nodes.driver_config import LinkSection

    assert drivers.link_names() == sorted(drivers.LINKS) == sorted(LinkSection.__struct_fields__)
    hints = get_type_hints(LinkSection)
    for name in drivers.LINKS:
        module = drivers.link_module(name)
        assert hints[name] is module.CONFIG is drivers.link_config(name)
        assert isinstance(module.EMULATED, bool) and module.DRIVER.name == name
    for path in ROOT.rglob("*.py"):
        if ".venv" in path.parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument" and any(
                    isinstance(a, ast.Constant) and a.value == "--link" for a in node.args):
                choices = [k.value for k in node.keywords if k.arg == "choices"]
                assert choices and not isinstance(choices[0], ast.List), \
                    f"{path.relative_to(ROOT)}:{node.lineno}: --link choices written by hand"


def test_the_learner_emulates_exactly_the_links_marked_emulated() -> None:
    """sim_learner may not import drivers, so its own table of emulators is checked against the registry here."""
    import drivers
    from sim_learner.emulator import EMULATORS

    assert sorted(EMULATORS) == [n for n in drivers.link_names() if drivers.link_module(n).EMULATED]
