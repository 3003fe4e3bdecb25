"""The learner's dynamics: a unicycle whose command response is distorted (the paper's learners).

The learner is a black box to the transfer code: something that takes a command and reports a pose. These models
are what stands behind that box in simulations and in the link emulators.

Paper, Eq. mpc_dynamicmodel_learner: the applied velocity is ``d(h(n(u)))`` per axis, where ``n`` normalises a
command by the learner's range to [0, 1], ``h`` distorts it, and ``d`` de-normalises. Commands are first clamped to
the learner's hard range (a real motor controller cannot do more than it can).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.paper import (  # noqa: F401  (re-exported: the sims' learners use the paper's ranges)
    EXP_LEARNER_V,
    EXP_LEARNER_W,
    MPC_LEARNER_V,
    MPC_LEARNER_W,
    MPC_TEACHER_V,
    MPC_TEACHER_W,
    PRIM_LEARNER_V,
    PRIM_LEARNER_W,
    PRIM_TEACHER_V,
    PRIM_TEACHER_W,
)
from transfer.teacher.unicycle import step as unicycle_step

Shape = Callable[[NDArray[np.float64]], NDArray[np.float64]]


def _identity(x: NDArray[np.float64]) -> NDArray[np.float64]:
    return x


def h_v_cubic(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Paper: ``h_v(v) = v^3`` on the normalised speed."""
    return v**3


def h_w_cubic(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Paper: ``h_w(w) = 4 (w - 0.5)^3 + 0.5`` on the normalised yaw rate (flat around the middle)."""
    return 4.0 * (w - 0.5) ** 3 + 0.5


# Eq. nonlinear_exp, highest power first. The paper prints "- 144.65 w^5"; with that sign the curve leaves [0, 1]
# (h(1) = -288), while "+ 144.65 w^5" gives a monotone curve with h(0) = 0, h(0.5) = 0.498, h(1) = 0.99, which is
# what the paper's Figure (nonlinear_exp) shows. We use the latter: a typesetting slip, not a different learner.
_H_W7 = (31.42, -109.91, 144.65, -86.98, 24.77, -5.08, 2.12, 0.0)


def h_w_poly7(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Paper, Eq. nonlinear_exp: the experiment's 7th-order yaw-rate distortion (sign of w^5 corrected, see above).

    Clipped to [0, 1] so the learner never leaves its own range.
    """
    return np.clip(np.polyval(_H_W7, w), 0.0, 1.0)


@dataclass(frozen=True)
class LearnerModel:
    """A degraded unicycle: commands clamped to ``v_range`` x ``w_range``, then ``d(h(n(u)))`` per axis.

    ``gain_v``/``gain_w`` scale the result afterwards (the per-axis scaled learner of the primitives case).
    """

    v_range: tuple[float, float]
    w_range: tuple[float, float]
    h_v: Shape = _identity
    h_w: Shape = _identity
    gain_v: float = 1.0
    gain_w: float = 1.0
    name: str = "learner"
    meta: dict[str, float] = field(default_factory=dict)

    def clamp(self, u: ArrayLike) -> NDArray[np.float64]:
        """The command the vehicle can take: each axis clipped to the learner's hard range."""
        c = np.asarray(u, dtype=float)
        return np.stack(
            [np.clip(c[..., 0], *self.v_range), np.clip(c[..., 1], *self.w_range)],
            axis=-1,
        )

    def response(self, u: ArrayLike) -> NDArray[np.float64]:
        """The body velocities ``(v, omega)`` the learner really moves with under command ``u``."""
        c = self.clamp(u)
        (v0, v1), (w0, w1) = self.v_range, self.w_range
        nv = (c[..., 0] - v0) / (v1 - v0)
        nw = (c[..., 1] - w0) / (w1 - w0)
        v = self.h_v(nv) * (v1 - v0) + v0
        w = self.h_w(nw) * (w1 - w0) + w0
        return np.stack([self.gain_v * v, self.gain_w * w], axis=-1)

    def step(
        self,
        state: ArrayLike,
        u: ArrayLike,
        dt: float,
        rng: np.random.Generator | None = None,
        pos_noise: float = 0.0,
    ) -> NDArray[np.float64]:
        """One Euler step under command ``u``; optional Gaussian position noise (std ``pos_noise`` m)."""
        out = unicycle_step(state, self.response(u), dt)  # the unicycle moving with the learner's real response
        if pos_noise > 0.0:
            if rng is None:
                raise ValueError("position noise needs an explicit random generator")
            out[..., :2] += rng.normal(0.0, pos_noise, size=out[..., :2].shape)
        return out


def mpc_learner() -> LearnerModel:
    """The MPC case's learner (Eq. mpc_dynamicmodel_learner, Table 2 simulation ranges)."""
    return LearnerModel(MPC_LEARNER_V, MPC_LEARNER_W, h_v_cubic, h_w_cubic, name="mpc-cubic")


def experiment_learner() -> LearnerModel:
    """The MPC experiment's Jackal alteration (h_v cubic, 7th-order h_w; Table 2 experiment ranges)."""
    return LearnerModel(EXP_LEARNER_V, EXP_LEARNER_W, h_v_cubic, h_w_poly7, name="exp-poly7")


def scaled_learner(gain_v: float = 1.2, gain_w: float = 1.6) -> LearnerModel:
    """The primitives case's learner: Table 1 ranges, each axis' response scaled by a constant gain."""
    return LearnerModel(
        PRIM_LEARNER_V, PRIM_LEARNER_W, gain_v=gain_v, gain_w=gain_w, name=f"scaled-{gain_v:g}-{gain_w:g}"
    )


def miswired_learner() -> LearnerModel:
    """A robot whose yaw answers the opposite way (a motor wired the wrong way round; v within +-0.5 m/s, omega
    within +-1 rad/s, both linear): every correction the teacher makes drives it farther off its path, so it runs
    away until the station's corridor stops it (docs/ARCHITECTURE.md, "The corridor, the fence and the pose jump")."""
    return LearnerModel((-0.5, 0.5), (-1.0, 1.0), gain_w=-1.0, name="miswired")


MODELS: dict[str, Callable[[], LearnerModel]] = {
    "mpc": mpc_learner,
    "experiment": experiment_learner,
    "scaled": scaled_learner,
    "miswired": miswired_learner,
}


def model_by_name(name: str) -> LearnerModel:
    """A learner model from its config name (``mpc``, ``experiment``, ``scaled``, ``miswired``)."""
    try:
        return MODELS[name]()
    except KeyError:
        raise ValueError(f"unknown learner model {name!r}; known: {', '.join(MODELS)}") from None
