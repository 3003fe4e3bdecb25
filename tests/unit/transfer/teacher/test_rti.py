"""transfer/teacher/rti.py: the MPC's real-time iteration, one dense QP per tick (its closed loop against the
reference is in test_mpc.py)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_learner.worlds import mpc_world
from transfer.domain import Bounds
from transfer.teacher.mpc import MpcConfig, MpcTeacher
from transfer.teacher.rti import _Rti
from transfer.teacher.unicycle import step


@pytest.mark.parametrize("solver", ["rti-qpoases", "rti-daqp"])
def test_a_qp_is_judged_solved_as_its_statistics_say(solver: str) -> None:
    """The real-time iteration reads qpOASES's success from its return flag, not from its statistics (a dictionary
    built per call): over solved QPs and starved ones (working-set changes used up, then a QP not solved) each
    verdict is the statistics' own, and a failure's status is the solver's text."""
    world = mpc_world(0.6)
    limits = Bounds((0.05, 0.3), (-0.2, 0.26))
    verdicts: list[tuple[bool, bool]] = []
    for max_iter in (60, 1, 0):
        mpc = MpcTeacher(MpcConfig(N=10, solver=solver, max_iter=max_iter))
        backend = mpc._backend
        assert isinstance(backend, _Rti)

        class Judged:
            """The solver's QP function, recording each evaluation's flag and statistics."""

            def __init__(self, qp) -> None:
                self.qp = qp

            def __getattr__(self, name: str):
                return getattr(self.qp, name)

            def __call__(self) -> None:
                self.qp()
                verdicts.append((self.qp.ret() == 0, bool(self.qp.stats()["success"])))

        for qp in backend.qps.values():
            qp.buf = Judged(qp.buf)
        x = world.start.copy()
        for _ in range(15):
            qp0 = len(verdicts)
            res = mpc.solve(x, world.path, limits, world.obstacles)
            assert res.ok == all(v[1] for v in verdicts[qp0:]), (max_iter, verdicts[qp0:], res.status)
            if not res.ok:
                assert res.status.startswith("QP: ") and "Successful" not in res.status
            x = step(x, res.u, 0.1)
    assert any(ok for _, ok in verdicts) and any(not ok for _, ok in verdicts)
    if solver == "rti-qpoases":
        assert all(flag == ok for flag, ok in verdicts), verdicts


def test_the_qp_holds_the_obstacle_slots_in_use_and_solves_as_the_full_one() -> None:
    """The QP of a tick holds the fixed rows and the rows of the fewest slot sizes that fit the obstacles in use
    (an unused slot's rows are never active): along the full-size world's closed loop, with none, one and two
    obstacles within reach, each tick's plan equals the plan of the QP with every slot's rows, from the same
    start, to the solver's tolerance."""
    world = mpc_world()
    limits = Bounds((0.05, 0.6), (-0.7854, 0.7854))
    cfg = MpcConfig(N=20, solver="rti-qpoases", max_obstacles=12)
    small, full = MpcTeacher(cfg), MpcTeacher(cfg)
    assert isinstance(small._backend, _Rti) and small._backend.sizes == (0, 2, 12)
    rows = {k: qp.rows for k, qp in small._backend.qps.items()}
    assert rows[12] - rows[0] == 12 * 20 and rows[2] - rows[0] == 2 * 20
    used: dict[int, int] = {}
    full_solve = full._backend.solve
    full._backend.solve = lambda p, s, U0, lim, cold, slots=None: full_solve(p, s, U0, lim, cold, None)  # every row
    x, worst = world.start.copy(), 0.0
    for _ in range(400):
        kept, _ = small.obstacles_that_matter(x, world.obstacles, limits)
        used[len(kept)] = used.get(len(kept), 0) + 1
        a = small.solve(x, world.path, limits, world.obstacles)
        b = full.solve(x, world.path, limits, world.obstacles)
        assert a.ok and b.ok
        worst = max(worst, float(np.max(np.abs(a.predicted - b.predicted))), float(np.max(np.abs(a.u - b.u))))
        full._prev_u, full._prev_pred, full.u_last = small._prev_u, small._prev_pred, small.u_last  # same start
        x = step(x, a.u, 0.1)
        if world.reached(x):
            break
    assert {0, 1, 2} <= set(used), used
    assert worst < 1e-6, worst
