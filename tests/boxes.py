"""The paper's MPC case as command boxes (Section 5.2, Table 2; the numbers are :mod:`transfer.paper`'s): the
teacher's ``TB`` and the cubic learner's ``LB``, which the tests of the transfer and of its figures draw on."""

from __future__ import annotations

import numpy as np

from transfer.domain import Bounds
from transfer.paper import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
from transfer.store import PairStore

#: the MPC teacher's (v, omega) box: v 0.05..0.6 m/s, omega -pi/4..pi/4 rad/s
TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
#: the cubic learner's (v, omega) box: v 0.05..0.3 m/s, omega -pi/16..pi/12 rad/s
LB = Bounds(MPC_LEARNER_V, MPC_LEARNER_W)


def affine_store(k_min: int = 1) -> tuple[PairStore, np.ndarray, np.ndarray]:
    """A store of refined pairs on an 11 x 11 grid of the learner's box, of a per-axis affine learner
    (teacher = a * learner + b): every mapper must reproduce it inside the hull."""
    a, b = np.array([1.3, 0.8]), np.array([0.01, 0.02])
    s = PairStore(LB, TB, k_min=k_min)
    g = np.linspace(0.0, 1.0, 11) * 0.98 + 0.01
    for x in g:
        for y in g:
            uL = LB.denormalise([x, y])
            s.add(a * uL + b, uL)
    return s, a, b
