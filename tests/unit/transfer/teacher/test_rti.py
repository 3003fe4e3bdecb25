"""transfer/teacher/rti.py: the MPC's real-time iteration, one dense QP per tick (its closed loop against the
reference is in test_mpc.py)."""

from __future__ import annotations

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

        backend.qp = Judged(backend.qp)
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
