"""The paper's MPC case as command boxes (Section 5.2, Table 2; the numbers are :mod:`transfer.paper`'s): the
teacher's ``TB`` and the cubic learner's ``LB``, which the tests of the transfer and of its figures draw on."""

from __future__ import annotations

from transfer.domain import Bounds
from transfer.paper import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W

#: the MPC teacher's (v, omega) box: v 0.05..0.6 m/s, omega -pi/4..pi/4 rad/s
TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
#: the cubic learner's (v, omega) box: v 0.05..0.3 m/s, omega -pi/16..pi/12 rad/s
LB = Bounds(MPC_LEARNER_V, MPC_LEARNER_W)
