"""What the learned limits know of their own edges after a change (docs/PAPER.md, "A learner that changes": "A side
whose edge is unknown" and "The slowing MPC where the limits need it"): :class:`EdgeWatch`, held by
:class:`transfer.limits.LearnerLimits`.

**A side whose edge is unknown.** A learned edge moves only by boundary pairs (the learner's extreme command on its
side), and those come when the teacher asks for that side's limit. After an edge was found moved by its own test
(``transfer/limits.py``, "An edge that moved") a side whose boundary pairs all date from before it says what the
learner could do, not what it can: on the SITL rover after a turn-rate cut, the side the rest of the path did not turn
hard kept its old edge for good. With change detection each edge that moved marks every other learned side *unknown*
until it has taken :data:`REPROBE_PAIRS` boundary pairs since (the edges' test finds a moved edge at its second), or
was probed :data:`REPROBE_TRIES` times without them (a learner that does not settle at its extreme within a probe
keeps the edge it had: no probe after that until the next change); a re-learned cell's own boundary pairs replace its
side's already (``LearnerLimits.forget``), and a cell re-learned elsewhere says nothing of an edge.
:meth:`EdgeWatch.reprobe` names the unknown sides a teacher command leans towards (at least :data:`REPROBE_LEAN` of
the way from the learned box's middle to that edge), at most one probe a side per :data:`REPROBE_GAP` commands, each
held for :data:`REPROBE_HOLD` commands, and :class:`transfer.step.TransferStep` sends the learner's extreme there for
those commands, only where it may explore (clear of obstacles) and inside a share of the corridor.

**A settled edge.** A learner whose response depends on its history (an acceleration limit that binds: ``sim drift
--scenario payload``) gives at its extreme command, the tick it is first sent, a pair short of its reach; such pairs
drew the learned top speed down, and the edges' test then found a "change" each time the learner had accelerated again
(5 to 11 times a run). With the change test, where the caller gives the command before a pair
(:meth:`transfer.store.PairStore.add`'s ``prev_u_L``), a boundary pair counts only when the command before it was at
the same extreme and the two pairs' responses agree within the change test's tolerance (:func:`unsettled`): the
learner's response is then conditioned on its previous command, and it has settled. A side's first pair too: the probe
of a never-driven limit is sent again each command until a boundary pair is taken (:mod:`transfer.policy`), so it holds
the extreme until the learner settled there (a first pair taken while the learner accelerated set the payload's top
speed low for good, and the teacher, bounded by it, never asked for more: a run of 200 s for 140). A probe of an
unknown side holds the extreme for :data:`REPROBE_HOLD` commands so that its second command's pair can count. Without
``prev_u_L`` (the station's pairs, each from a command held until it settled) nothing changes.

**The slowing MPC where the limits need it.** The teacher's MPC can slow down for a bend its yaw-rate bound cannot
turn at the top speed (``curve_margin``); that changes the paper's experiment, where the learned limits are what they
were from the start. :meth:`EdgeWatch.turn_lost` says when they are not: a yaw-rate side's edge has come inside the
widest it held (once a mean of :data:`REACH_PAIRS` boundary pairs) by more than :data:`TURN_LOST` (a learner that lost
reach: a sagging battery, a dragging wheel), and the MPC slows for bends from then on, as long as it holds.

Pure: no I/O, no clock; Python floats (one pair a tick).
"""

from __future__ import annotations

import math

#: boundary pairs a side takes after a change before its edge is known again (the edges' test alarms at the second)
REPROBE_PAIRS = 2
#: an unknown side is probed when the teacher's command leans this far towards it: a share of the way from the
#: learned box's middle to the side's edge (normalised teacher units)
REPROBE_LEAN = 0.5
#: probes of an unknown side without a settled boundary pair before it is kept as it is
REPROBE_TRIES = 3
#: commands a probe of an unknown side holds the learner's extreme (the second one's pair is settled)
REPROBE_HOLD = 2
#: commands between two probes of one side (1 s at 10 Hz: the teacher corrects the probe's command before the next)
REPROBE_GAP = 10
#: a yaw-rate edge this far inside the widest it held (normalised teacher units, the store's ``change_tol``) has lost
#: reach: the slowing MPC is on
TURN_LOST = 0.02
#: boundary pairs a side's mean must hold before its edge counts as reached
REACH_PAIRS = 5


def unsettled(t: float, l: float, prev_t: float, prev_l: float, tol: float, settle: float) -> bool:
    """Whether a pair whose normalised teacher and learner parts on one axis are ``t`` and ``l``, after a pair
    ``(prev_t, prev_l)`` the tick before (NaN: none), is at an edge of that axis before the learner settled there:
    the command before it was not at the same extreme, or the two pairs' responses differ by more than ``settle``
    (module docstring, "A settled edge"). ``tol``: the boundary's."""
    if l >= 1.0 - tol:
        at = prev_l >= 1.0 - tol
    elif l <= tol:
        at = prev_l <= tol
    else:
        return False
    return not (at and abs(t - prev_t) <= settle)


class EdgeWatch:
    """Per axis side (``[axis][side]``, side 0 the lower): the boundary pairs it still needs to be known after a
    change, the commands since its last probe, and the widest edge it held (module docstring)."""

    def __init__(self) -> None:
        self.unknown = [[0, 0], [0, 0]]
        self.tries = [[0, 0], [0, 0]]  # probes of each unknown side since it was marked
        self.since = [[REPROBE_GAP, REPROBE_GAP], [REPROBE_GAP, REPROBE_GAP]]
        self.hold: list[tuple[int, int]] = []  # the sides the last probe began, held for the next command
        self.widest = [[math.nan, math.nan], [math.nan, math.nan]]
        self.reprobes = 0  # probes of unknown sides sent (``probed``)

    def changed(self, counts: list[list[int]]) -> None:
        """The learner changed: every side with a learned edge (``counts[a][side]`` boundary pairs; a side never
        driven is probed by the policy as ever) is unknown until it takes :data:`REPROBE_PAIRS` boundary pairs."""
        for a in (0, 1):
            for side in (0, 1):
                if counts[a][side] > 0:
                    self.unknown[a][side], self.tries[a][side] = REPROBE_PAIRS, 0
                    self.since[a][side] = max(self.since[a][side], REPROBE_GAP - 1)  # probed at the next lean

    def known(self, a: int, side: int, pairs: int = REPROBE_PAIRS) -> None:
        """Side ``side`` of axis ``a`` took ``pairs`` boundary pairs since the change (or was learned again from that
        many of its own)."""
        self.unknown[a][side] = max(0, self.unknown[a][side] - pairs)

    def widen(self, lo: list[float], hi: list[float], counts_lo: list[int], counts_hi: list[int]) -> None:
        """The learned box's normalised edges after a boundary pair: a side whose mean holds :data:`REACH_PAIRS`
        pairs or more has reached at least that far."""
        for a in (0, 1):
            if counts_hi[a] >= REACH_PAIRS and not hi[a] <= self.widest[a][1]:
                self.widest[a][1] = hi[a]
            if counts_lo[a] >= REACH_PAIRS and not lo[a] >= self.widest[a][0]:
                self.widest[a][0] = lo[a]

    def turn_lost(self, lo: float, hi: float, tol: float = TURN_LOST) -> bool:
        """Whether a yaw-rate edge (normalised ``lo``, ``hi``) is more than ``tol`` inside the widest it held."""
        w_lo, w_hi = self.widest[1]
        return (not math.isnan(w_hi) and w_hi - hi > tol) or (not math.isnan(w_lo) and lo - w_lo > tol)

    def pending(self) -> bool:
        """Whether a side is unknown or a probe is being held: :meth:`reprobe` may name a side."""
        return bool(self.hold) or any(self.unknown[0]) or any(self.unknown[1])

    def reprobe(self, t_n: list[float], lo: list[float], hi: list[float]) -> list[tuple[int, int]]:
        """The unknown sides (axis, side) teacher command ``t_n`` (normalised) leans towards, each at most once per
        :data:`REPROBE_GAP` calls; counts the call for every side."""
        out = []
        held, self.hold = self.hold, []
        for a in (0, 1):
            mid = 0.5 * (lo[a] + hi[a])
            for side, edge in ((0, lo[a]), (1, hi[a])):
                self.since[a][side] += 1
                if (a, side) in held and self.since[a][side] < REPROBE_HOLD:
                    out.append((a, side))  # the probe's next command: held at the extreme
                    continue
                if self.unknown[a][side] <= 0 or self.since[a][side] < REPROBE_GAP:
                    continue
                half = abs(edge - mid)
                if half > 0.0 and (t_n[a] - mid) * (1 if side else -1) >= REPROBE_LEAN * half:
                    out.append((a, side))
        for a, side in out:
            if (a, side) not in held:
                self.since[a][side] = 0
                self.reprobes += 1
                self.hold.append((a, side))
                self.tries[a][side] += 1
                if self.tries[a][side] >= REPROBE_TRIES:  # its last probe (held all the same)
                    self.unknown[a][side] = 0
        return out


__all__ = ["REACH_PAIRS", "REPROBE_GAP", "REPROBE_HOLD", "REPROBE_LEAN", "REPROBE_PAIRS", "REPROBE_TRIES", "TURN_LOST",
           "EdgeWatch",
           "unsettled"]
