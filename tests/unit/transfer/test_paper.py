"""transfer/paper.py: the paper's command ranges (Tables 1 and 2), pure data.

What the module promises is that they are the one source of these numbers: each range is a valid box, each
learner's box lies inside its teacher's (the paper's learners are the limited ones), and the simulations' learners
and the station's default configuration take their numbers from here."""

from __future__ import annotations

import math

from transfer import paper
from transfer.domain import Bounds


def _box(v: tuple[float, float], w: tuple[float, float]) -> Bounds:
    return Bounds(v, w)


def test_every_range_is_a_valid_box_and_each_learner_sits_inside_its_teacher() -> None:
    cases = [
        ((paper.MPC_LEARNER_V, paper.MPC_LEARNER_W), (paper.MPC_TEACHER_V, paper.MPC_TEACHER_W)),
        ((paper.EXP_LEARNER_V, paper.EXP_LEARNER_W), (paper.MPC_TEACHER_V, paper.MPC_TEACHER_W)),
        ((paper.PRIM_LEARNER_V, paper.PRIM_LEARNER_W), (paper.PRIM_TEACHER_V, paper.PRIM_TEACHER_W)),
    ]
    for learner, teacher in cases:
        lb, tb = _box(*learner), _box(*teacher)
        assert tb.contains(lb.lo) and tb.contains(lb.hi)
        assert lb.span[0] < tb.span[0] and lb.span[1] < tb.span[1]


def test_the_tables_values() -> None:
    """Table 2 (MPC case), Section 6 (the real robot's learner) and Table 1 (primitives), as the paper prints them."""
    table = {
        "MPC_TEACHER_V": (0.05, 0.6), "MPC_TEACHER_W": (-math.pi / 4, math.pi / 4),
        "MPC_LEARNER_V": (0.05, 0.3), "MPC_LEARNER_W": (-math.pi / 16, math.pi / 12),
        "EXP_LEARNER_V": (0.05, 0.2), "EXP_LEARNER_W": (-math.pi / 8, math.pi / 8),
        "PRIM_TEACHER_V": (0.0, 3.0), "PRIM_TEACHER_W": (-math.pi / 3, math.pi / 3),
        "PRIM_LEARNER_V": (0.0, 1.0), "PRIM_LEARNER_W": (-math.pi / 8, math.pi / 8),
    }
    for name, want in table.items():
        assert getattr(paper, name) == want, name


def test_the_station_defaults_and_the_simulations_learner_take_their_numbers_from_here() -> None:
    from bridge.core.config import DEFAULT_LEARNER_BOUNDS, DEFAULT_TEACHER_BOUNDS
    from sim_learner.dynamics import mpc_learner

    assert tuple(DEFAULT_TEACHER_BOUNDS.v) == paper.MPC_TEACHER_V
    assert tuple(DEFAULT_TEACHER_BOUNDS.w) == paper.MPC_TEACHER_W
    assert tuple(DEFAULT_LEARNER_BOUNDS.v) == paper.MPC_LEARNER_V
    assert tuple(DEFAULT_LEARNER_BOUNDS.w) == paper.MPC_LEARNER_W
    learner = mpc_learner()
    assert tuple(learner.v_range) == paper.MPC_LEARNER_V and tuple(learner.w_range) == paper.MPC_LEARNER_W
