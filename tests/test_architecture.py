"""The shape docs/ARCHITECTURE.md promises, checked from the code's own imports (every import statement, also the
ones inside functions): no cycle between modules, a pure method, a leaf wire schema, a station that knows no
simulator, and docstrings that cite only what the repository contains."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("transfer", "bridge", "drivers", "sim_learner")


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


GRAPH = {m: _imports(m) for m in MODULES}


def _reach(start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for n in GRAPH[todo.pop()]:
            if n not in seen:
                seen.add(n)
                todo.append(n)
    return seen


def test_no_module_imports_one_that_imports_it_back() -> None:
    cycles = sorted(m for m in MODULES if m in _reach(m))
    assert not cycles, f"import cycles through: {cycles}"


def test_the_method_is_pure_and_depends_on_no_io_package() -> None:
    for m in MODULES:
        if m.startswith("transfer"):
            assert not [n for n in GRAPH[m] if not n.startswith("transfer")], m
            text = MODULES[m].read_text()
            assert not re.search(r"^\s*(import|from)\s+(zenoh|socket|threading|time|can|pymavlink)\b", text, re.M), m


def test_the_wire_schema_is_a_leaf() -> None:
    assert GRAPH["bridge.wire"] == set()


def test_the_station_knows_no_simulator() -> None:
    assert not [m for m in _reach("bridge.station") if m.startswith("sim_learner")]


@pytest.mark.parametrize("mod", ["bridge.driver_host", "drivers.can", "drivers.mavlink", "drivers.udp"])
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
