"""The paper's command ranges (Tables 1 and 2): the teachers' and learners' (v, omega) boxes of its experiments.

Pure data. The simulations' learners (``sim_learner.dynamics``) and the station's default configuration both take
their numbers from here, so "the paper's MPC case" means one thing everywhere.
"""

from __future__ import annotations

import math

#: MPC case (Section 5.2, Table 2): the teacher's and the cubic learner's ranges, m/s and rad/s
MPC_TEACHER_V = (0.05, 0.6)
MPC_TEACHER_W = (-math.pi / 4, math.pi / 4)
MPC_LEARNER_V = (0.05, 0.3)
MPC_LEARNER_W = (-math.pi / 16, math.pi / 12)
#: the real-robot experiment's learner (Section 6)
EXP_LEARNER_V = (0.05, 0.2)
EXP_LEARNER_W = (-math.pi / 8, math.pi / 8)
#: motion-primitive case (Section 5.1, Table 1)
PRIM_TEACHER_V = (0.0, 3.0)
PRIM_TEACHER_W = (-math.pi / 3, math.pi / 3)
PRIM_LEARNER_V = (0.0, 1.0)
PRIM_LEARNER_W = (-math.pi / 8, math.pi / 8)
