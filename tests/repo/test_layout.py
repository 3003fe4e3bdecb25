"""The tests mirror the code, so a newcomer finds a module's tests where they look first: ``pkg/mod.py`` has its unit
tests in ``tests/unit/pkg/test_mod.py`` (a private module's leading underscore dropped; several files
``test_mod_*.py`` when one would be long); what starts processes, routers or real-time loops lives in
``tests/integration/``, and checks of the repository itself in ``tests/repo/``. A module whose tests can only be
end-to-end is listed below with the file that tests it. Pure file reading: no import of the project."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("transfer", "bridge", "drivers", "sim_learner", "bench")
#: modules whose tests are not unit tests, and where they are (each must exist)
ELSEWHERE = {
    "sim_learner/sitl.py": "tests/integration/test_sitl.py",  # ArduPilot's SITL binary, real time
    "bridge/__main__.py": "tests/repo/test_cli.py",
}
#: bench/ is the benchmarks: its unit tests are where a benchmark has logic of its own worth testing
OPTIONAL = ("bench/",)


def _modules() -> list[str]:
    out = []
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            rel = p.relative_to(ROOT).as_posix()
            if p.name == "__init__.py" or "/fuzz/" in rel:
                continue
            out.append(rel)
    return out


def _unit_tests_of(module: str) -> list[Path]:
    path = Path(module)
    stem = path.stem.lstrip("_")
    folder = ROOT / "tests" / "unit" / path.parent
    return sorted(folder.glob(f"test_{stem}.py")) + sorted(folder.glob(f"test_{stem}_*.py"))


def test_every_module_has_its_unit_tests_where_a_newcomer_looks() -> None:
    missing = [m for m in _modules() if not m.startswith(OPTIONAL) and m not in ELSEWHERE and not _unit_tests_of(m)]
    assert not missing, "modules without tests/unit/<package>/test_<module>.py:\n" + "\n".join(missing)


def test_the_modules_tested_elsewhere_name_files_that_exist() -> None:
    for module, test in ELSEWHERE.items():
        assert (ROOT / module).exists(), f"{module} is gone: drop it from ELSEWHERE"
        assert (ROOT / test).exists(), f"{module}'s tests {test} do not exist"


def test_every_test_file_is_in_one_of_the_three_places() -> None:
    loose = sorted(p.name for p in (ROOT / "tests").glob("test_*.py"))
    assert not loose, f"test files outside tests/unit, tests/integration and tests/repo: {loose}"
    for unit in (ROOT / "tests" / "unit").rglob("test_*.py"):
        rel = unit.relative_to(ROOT / "tests" / "unit").parent
        assert (ROOT / rel).is_dir(), f"{unit.relative_to(ROOT)} mirrors no package of the code ({rel}/)"
