"""The one transfer step: a teacher command mapped to the learner command to send, exploring only where it is safe.

The station and the paper's simulations both map every teacher command through :class:`TransferStep`, so they
follow one rule:

- exploration is allowed when the step is configured to explore and, when the pose and the mission are known, the
  pose is at least ``clearance`` from every obstacle's edge (:meth:`transfer.mission.Mission.may_explore`);
- where it is allowed, the policy explores by its own rule (:class:`~transfer.policy.GuidedPolicy` steered by the
  teacher's plan, :class:`~transfer.policy.PaperPolicy` as published, ignoring the plan);
- where it is not (near obstacles, or exploration off), no policy perturbs: the command is the guided mapping
  without perturbation (the region's map, its barycentric fallback, or the estimate relative to the learned
  region), and the result says so (``Mapped.vetoed``).

The teacher's plan (an MPC's predicted states) becomes the policy's hint of the next ``plan_hint`` commands
(:func:`~transfer.policy.planned_commands`).

After a change of the learner (the store's change detection), a side of the learned limits whose edge is unknown is
probed again (``transfer/limits_watch.py``): where exploration is allowed and the pose is within
:data:`~transfer.feasibility.CORRIDOR_SHARE` of the corridor (when the caller gives it), a command that leans towards
such a side is sent at the learner's extreme on that axis, the other axis as mapped (a yaw-rate probe of a learner
that cannot turn in place at its top speed, as the policy's own probe), for the probe's commands (``"perturb"``).
Pure: no I/O, no clock.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike, NDArray

from transfer.feasibility import CORRIDOR_SHARE
from transfer.mission import EXPLORE_CLEARANCE, Mission
from transfer.policy import Mapped, Policy, planned_commands

#: planned teacher commands passed to the policy as its hint (1 s of a 10 Hz MPC's plan)
PLAN_HINT = 10


class TransferStep:
    """Maps teacher commands with one policy under the one exploration rule (module docstring)."""

    def __init__(self, policy: Policy, *, dt: float, explore: bool = True, clearance: float = EXPLORE_CLEARANCE,
                 plan_hint: int = PLAN_HINT, defer: bool = False) -> None:
        """``policy``: the transfer policy; ``dt``: the teacher's control period (to read its plan); ``explore``:
        whether exploration is on at all; ``clearance``: no exploration closer than this to an obstacle's edge, m;
        ``plan_hint``: how many planned commands steer the exploration; ``defer``: the work a command may leave for
        later (the guided policy's hole search) is done by :meth:`background`, between commands, not in
        :meth:`map`."""
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        self.policy = policy
        self.dt = float(dt)
        self.explore = bool(explore)
        self.clearance = float(clearance)
        self.plan_hint = int(plan_hint)
        self.defer = bool(defer) and hasattr(policy, "search_step")
        if self.defer:
            policy.defer_search = True  # type: ignore[attr-defined]

    def background(self) -> bool:
        """With ``defer``: the work the last command left for later, done now (before the next command: then the
        commands are those of a step that did it in :meth:`map`, but for a hole's burst beginning a command
        later; :meth:`transfer.policy.GuidedPolicy.search_step`); True when there was some."""
        return self.defer and self.policy.search_step()  # type: ignore[attr-defined]

    @property
    def store(self):
        """The policy's pair store."""
        return self.policy.store

    def may_explore(self, pose: ArrayLike | None, mission: Mission | None) -> bool:
        """Is exploration allowed for a command sent at ``pose`` (``(x, y, ...)``; None: unknown) on ``mission``?"""
        if not self.explore:
            return False
        if pose is None or mission is None:
            return True
        return mission.may_explore(np.asarray(pose, dtype=float)[:2], self.clearance)

    def map(self, u_T: ArrayLike, pose: ArrayLike | None = None, mission: Mission | None = None,
            predicted: ArrayLike | None = None, corridor_m: float | None = None) -> Mapped:
        """The learner command for teacher command ``u_T`` sent at ``pose`` on ``mission``; ``predicted``: the
        teacher's predicted states ``(N + 1, 3)``, if it has a plan; ``corridor_m``: the mission's corridor (a
        re-probe only within its :data:`~transfer.feasibility.CORRIDOR_SHARE`; None: not checked)."""
        explore = self.may_explore(pose, mission)
        plan = None
        if predicted is not None:  # read only if the policy explores next to a configured cell (a few % of commands)
            def plan() -> NDArray[np.float64]:
                return planned_commands(predicted, self.dt, self.plan_hint)
        m = self.policy.map(u_T, plan=plan, explore=explore)
        if not explore:
            return dataclasses.replace(m, vetoed=True)
        if m.method != "perturb" and self.store.adapt:
            return self._reprobe(m, u_T, pose, mission, corridor_m)
        return m

    def _reprobe(self, m: Mapped, u_T: ArrayLike, pose: ArrayLike | None, mission: Mission | None,
                 corridor_m: float | None) -> Mapped:
        """``m``, or the probe of a side whose edge is unknown after a change (module docstring)."""
        store = self.store
        if not store.limits.watch.pending():  # nothing unknown (nearly every command): no projection, no probe
            return m
        if corridor_m is not None and pose is not None and mission is not None:
            _, off = mission.path.project(np.asarray(pose, dtype=float)[:2])
            if off > CORRIDOR_SHARE * corridor_m:
                return m
        sides = store.limits.reprobe(store.teacher_bounds.normalise(np.asarray(u_T, dtype=float)))
        if not sides:
            return m
        lb = store.learner_bounds
        u = np.array(m.u_L, dtype=float)
        for a, side in sides:
            u[a] = lb.hi[a] if side else lb.lo[a]
            if a == 1 and getattr(self.policy, "turn_probe", "") == "at-top-speed":
                u[0] = lb.hi[0]  # a learner that cannot turn in place shows its turn at its top speed
        return dataclasses.replace(m, u_L=u, method="perturb")


__all__ = ["PLAN_HINT", "TransferStep"]
