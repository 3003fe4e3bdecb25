"""The worlds of the paper's experiments, as the mission files shipped with scmbridge (``bridge/missions/``).

Two sizes: the MPC case (teacher v <= 0.6 m/s, learner v <= 0.3 m/s) and the motion-primitive case (teacher
v <= 3 m/s, learner v <= 1 m/s, primitives 1 s long), the second a scaled copy of the first's S with its own
obstacles. The simulations, the demo and the station all read the same files.
"""

from __future__ import annotations

from bridge.core.config import load_mission
from transfer.mission import Mission

#: the simulations' name for a mission
World = Mission


def mpc_world(scale: float = 1.0) -> Mission:
    """The MPC case (mission ``paper-s-path``): an 8 m S-path, obstacles on the outside of both bends and beside the
    middle, a start 0.3 m beside the path facing 45 degrees away from it. ``scale`` < 1 shortens it (tests)."""
    m = load_mission("paper-s-path")
    return m if scale == 1.0 else m.scaled(scale)


def primitives_world() -> Mission:
    """The motion-primitive case (mission ``paper-primitives-s-path``): the same S scaled by 4 (32 m)."""
    return load_mission("paper-primitives-s-path")
