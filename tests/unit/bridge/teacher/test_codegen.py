"""The MPC's compiled code: built once with the machine's C compiler, cached, the same results as the interpreted
functions, adopted by a running station between two ticks, and a clear one-line fallback without a compiler."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from bridge.teacher import codegen
from sim_learner.worlds import mpc_world
from transfer.domain import Bounds
from transfer.teacher.mpc import MpcConfig, MpcTeacher
from transfer.teacher.unicycle import step

#: a small problem: it compiles in a second or two
SMALL = MpcConfig(N=6, max_obstacles=2, solver="rti-qpoases")
LIMITS = Bounds((0.05, 0.3), (-0.5, 0.5))

needs_cc = pytest.mark.skipif(codegen.c_compiler() is None, reason="no C compiler on this machine")


@pytest.fixture(autouse=True)
def _compile(monkeypatch, tmp_path) -> None:
    """These tests build for real, each into a cache of its own, with no memory of earlier builds or warnings."""
    monkeypatch.delenv("SCMBRIDGE_NO_COMPILE", raising=False)
    monkeypatch.setenv("SCMBRIDGE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(codegen, "_loaded", {})
    monkeypatch.setattr(codegen, "_warned", set())


def _drive(mpc: MpcTeacher, steps: int = 40) -> list[np.ndarray]:
    world = mpc_world(0.6)
    x, out = world.start.copy(), []
    for _ in range(steps):
        r = mpc.solve(x, world.path, LIMITS, world.obstacles)
        assert r.ok
        out.append(r.u)
        x = step(x, r.u, SMALL.dt)
    return out


@needs_cc
def test_compiled_code_gives_the_interpreted_results_and_is_built_once(tmp_path) -> None:
    interpreted = MpcTeacher(SMALL)
    compiled = MpcTeacher(SMALL, compiler=codegen.compile_functions)
    assert compiled.compiled and not interpreted.compiled
    libs = list((tmp_path / "cache" / "mpc").glob("kernels-*.so"))
    assert len(libs) == 1
    np.testing.assert_allclose(_drive(compiled), _drive(interpreted), rtol=0, atol=1e-9)
    # another MPC of the same problem, in this process or (with an empty memory) another: no second build
    built_at = libs[0].stat().st_mtime_ns
    codegen._loaded.clear()
    again = MpcTeacher(SMALL, compiler=codegen.compile_functions)
    assert again.compiled and libs[0].stat().st_mtime_ns == built_at
    assert list((tmp_path / "cache" / "mpc").glob("kernels-*.so")) == libs


@needs_cc
def test_a_station_adopts_the_compiled_code_between_ticks() -> None:
    from bridge.nodes.station import KernelBuild

    teacher = MpcTeacher(SMALL)
    build = KernelBuild(teacher)
    assert build.done.wait(120), "the build did not finish"
    assert not teacher.compiled  # nothing changes until the loop adopts it
    assert build.adopt(teacher) and teacher.compiled
    assert not build.adopt(teacher)
    other = MpcTeacher(SMALL)  # another robot of the same process: the same build serves it
    assert build.adopt(other) and other.compiled
    assert all(np.isfinite(u).all() for u in _drive(teacher, 5))


def test_without_a_compiler_the_mpc_runs_interpreted_and_says_so_once(monkeypatch, caplog) -> None:
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setenv("PATH", "")
    assert codegen.c_compiler() is None
    with caplog.at_level(logging.WARNING, logger="scmbridge.codegen"):
        a = MpcTeacher(SMALL, compiler=codegen.compile_functions)
        b = MpcTeacher(SMALL, compiler=codegen.compile_functions)
    assert not a.compiled and not b.compiled
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "no C compiler" in warnings[0] and "\n" not in warnings[0]
    assert all(np.isfinite(u).all() for u in _drive(a, 5))


def test_a_failing_compiler_falls_back_with_its_reason(monkeypatch, tmp_path, caplog) -> None:
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\necho 'cc: fatal error: no space left' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    with caplog.at_level(logging.WARNING, logger="scmbridge.codegen"):
        mpc = MpcTeacher(SMALL, compiler=codegen.compile_functions)
    assert not mpc.compiled
    assert any("no space left" in r.getMessage() for r in caplog.records)
    assert not list((tmp_path / "cache" / "mpc").glob("*.so"))


def test_the_suite_stations_run_interpreted_on_request(monkeypatch) -> None:
    monkeypatch.setenv("SCMBRIDGE_NO_COMPILE", "1")
    assert not MpcTeacher(SMALL, compiler=codegen.compile_functions).compiled
