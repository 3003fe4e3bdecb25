"""What the learned limits know of their edges after a change (``transfer/limits_watch.py``): a side whose edge is
unknown is probed again, inside the corridor and away from obstacles, and the slowing MPC is on where the learned limits
lost reach."""

from __future__ import annotations

import numpy as np
import pytest

from tests.boxes import LB, TB
from transfer.limits import calibration_commands
from transfer.limits_watch import REPROBE_GAP, REPROBE_HOLD, REPROBE_PAIRS, REPROBE_TRIES
from transfer.mission import Mission
from transfer.policy import make_policy
from transfer.step import TransferStep
from transfer.store import PairStore
from transfer.teacher.path import Polyline

#: a teacher command that leans towards the learner's right turn (the lower yaw-rate side), at a mid speed
RIGHT = np.array([0.15, 0.8 * LB.w[0]])


def _learned(adapt: bool = True) -> PairStore:
    """A learner that does what it is told (teacher equivalent = learner command), its box driven four times over a
    5 x 5 grid of commands, both locks of each axis among them."""
    s = PairStore(LB, TB, k_min=2, adapt=adapt)
    for _ in range(4):
        for lcmd in calibration_commands(LB, 5):
            s.add(lcmd, lcmd)
    return s


def _left_turn_cut(s: PairStore) -> None:
    """The learner's left lock now turns 60 % of what it did, shown by pairs at that lock until its edge is learned
    again (the edges' test finds it at its second such pair)."""
    for _ in range(3):
        s.add([0.2, 0.6 * LB.w[1]], [0.2, LB.w[1]])


def test_after_a_change_the_other_learned_sides_are_unknown_until_two_pairs_at_their_edge() -> None:
    s = _learned()
    lim = s.limits
    assert lim.relearned == 0 and not any(map(any, lim.watch.unknown)) and lim.reprobe(TB.normalise(RIGHT)) == []
    _left_turn_cut(s)
    assert lim.relearned == 1
    # the left side was learned again from its pairs since the change; the others learned before it are unknown
    assert lim.watch.unknown == [[REPROBE_PAIRS, REPROBE_PAIRS], [REPROBE_PAIRS, 0]]
    # a command that leans to the right names that side for REPROBE_HOLD commands, once per REPROBE_GAP commands;
    # one that goes straight, none
    for _ in range(2):
        assert [lim.reprobe(TB.normalise(RIGHT)) for _ in range(REPROBE_HOLD)] == [[(1, 0)]] * REPROBE_HOLD
        assert all(lim.reprobe(TB.normalise(RIGHT)) == [] for _ in range(REPROBE_GAP - REPROBE_HOLD))
    assert all(lim.reprobe(TB.normalise([0.15, 0.0])) == [] for _ in range(2 * REPROBE_GAP))
    assert lim.watch.reprobes == 2
    # two settled pairs at the right lock (the first of three after another pair is not): known again (the same
    # reach: nothing moves)
    right = lim.box.w[0]
    for k in range(REPROBE_PAIRS + 1):
        assert lim.watch.unknown[1][0] == min(REPROBE_PAIRS, REPROBE_PAIRS + 1 - k)
        s.add([0.15, LB.w[0]], [0.15, LB.w[0]], prev_u_L=[0.15, LB.w[0]])
    assert lim.watch.unknown[1][0] == 0 and lim.box.w[0] == pytest.approx(right)
    assert all(lim.reprobe(TB.normalise(RIGHT)) == [] for _ in range(2 * REPROBE_GAP))


def test_a_side_probed_without_a_settled_pair_is_kept_after_its_last_try() -> None:
    """A learner that does not settle at its extreme within a probe (its pairs there are not taken): the side is probed
    REPROBE_TRIES times, each held for REPROBE_HOLD commands, then kept as it is until the next change; a cell
    re-learned elsewhere does not mark it again, an edge that moves does."""
    s = _learned()
    _left_turn_cut(s)
    lim = s.limits
    probes = [lim.reprobe(TB.normalise(RIGHT)) != [] for _ in range(REPROBE_GAP * (REPROBE_TRIES + 2))]
    assert sum(probes) == REPROBE_TRIES * REPROBE_HOLD and lim.watch.unknown[1][0] == 0
    for _ in range(3):  # the left edge moves again: the right side is unknown again
        s.add([0.2, 0.3 * LB.w[1]], [0.2, LB.w[1]])
    assert lim.relearned == 2 and lim.watch.unknown[1][0] == REPROBE_PAIRS


def test_without_change_detection_no_side_is_ever_unknown() -> None:
    s = _learned(adapt=False)
    _left_turn_cut(s)
    assert s.limits.relearned == 0
    assert all(s.limits.reprobe(TB.normalise(RIGHT)) == [] for _ in range(2 * REPROBE_GAP))


def test_the_transfer_step_probes_an_unknown_side_at_the_learners_extreme_only_where_it_may_explore() -> None:
    """The probe goes to the learner's right lock, the speed as mapped, tagged ``perturb``; not near an obstacle
    (exploration's rule), not farther from the path than a quarter of the corridor, not with exploration off."""
    mission = Mission("m", Polyline(np.array([[0.0, 0.0], [5.0, 0.0]])), np.array([[2.0, 1.0, 0.5]]), 0.2)
    on_path, near, off_path = np.array([0.0, 0.0, 0.0]), np.array([2.0, 0.4, 0.0]), np.array([4.0, -0.3, 0.0])
    for where, corridor, probes in ((on_path, 1.0, True), (near, 1.0, False), (off_path, 1.0, False),
                                    (off_path, 2.0, True), (off_path, None, True)):
        s = _learned()
        _left_turn_cut(s)
        step = TransferStep(make_policy(s, "scm", seed=0), dt=0.1, clearance=0.3)
        m = step.map(RIGHT, where, mission, corridor_m=corridor)
        assert (m.method == "perturb") == probes, (where, corridor)
        if probes:
            assert m.u_L[1] == LB.w[0] and m.u_L[0] == pytest.approx(RIGHT[0], abs=0.01)
        else:
            assert m.u_L[1] > LB.w[0]
    s = _learned()
    _left_turn_cut(s)
    off = TransferStep(make_policy(s, "scm", seed=0), dt=0.1, explore=False)
    assert off.map(RIGHT, on_path, mission).method != "perturb"
    # the paper's store: the same command is mapped, never probed
    paper = _learned(adapt=False)
    _left_turn_cut(paper)
    step = TransferStep(make_policy(paper, "scm", seed=0), dt=0.1)
    assert all(step.map(RIGHT).method != "perturb" for _ in range(2 * REPROBE_GAP))


def test_a_yaw_rate_probe_of_a_learner_that_cannot_turn_in_place_is_sent_at_its_top_speed() -> None:
    s = _learned()
    _left_turn_cut(s)
    step = TransferStep(make_policy(s, "scm", seed=0, turn_probe="at-top-speed"), dt=0.1)
    m = step.map(RIGHT)
    assert m.method == "perturb" and m.u_L[1] == LB.w[0] and m.u_L[0] == LB.v[1]


def test_with_change_detection_a_learned_edge_takes_only_pairs_after_the_learner_settled_at_its_extreme() -> None:
    """A learner with an acceleration limit: commanded its top speed it reaches 60 % of it, then 85 %, then all of it.
    Given the command before each pair, the pairs before it settled (after another command, or a response that
    still changed) do not move the learned top speed (nor alarm its test, however often they come); the next one, two
    pairs at the top that agree, does; so for a side's first. Without the previous command, or without change detection
    (the paper's), every boundary pair counts."""
    top, mid = np.array([LB.v[1], 0.0]), np.array([0.1, 0.0])
    for adapt, give_prev in ((True, True), (True, False), (False, True)):
        s = _learned(adapt)
        before = s.limits.box.v[1]
        n = s.limits.version  # moves with every boundary pair taken
        for _ in range(12):  # accelerating from a mid command onto the top one, again and again
            s.add(mid, mid, prev_u_L=mid if give_prev else None)
            s.add([0.6 * LB.v[1], 0.0], top, prev_u_L=mid if give_prev else None)
            s.add([0.85 * LB.v[1], 0.0], top, prev_u_L=top if give_prev else None)
        if adapt and give_prev:
            assert s.limits.box.v[1] == pytest.approx(before) and s.limits.relearned == 0
            assert s.limits.version == n
            s.add(top, top, prev_u_L=top)
            assert s.limits.version == n  # the response still changed
            s.add(top, top, prev_u_L=top)
            assert s.limits.version == n + 1 and s.limits.box.v[1] == pytest.approx(before)
        else:
            assert s.limits.box.v[1] < before - 0.01
    # a side's first pair too (the probe of a never-driven limit is sent again until one is taken); not the paper's
    for adapt in (True, False):
        fresh = PairStore(LB, TB, k_min=2, adapt=adapt)
        fresh.add([0.6 * LB.v[1], 0.0], top, prev_u_L=mid)
        assert fresh.limits.bcnt_hi[0] == (0 if adapt else 1)
        fresh.add([0.85 * LB.v[1], 0.0], top, prev_u_L=top)
        fresh.add(top, top, prev_u_L=top)
        fresh.add(top, top, prev_u_L=top)
        assert fresh.limits.bcnt_hi[0] == (1 if adapt else 4)
        assert fresh.limits.box.v[1] == pytest.approx(LB.v[1] if adapt else (3.45 / 4) * LB.v[1])


def test_the_limits_lost_turn_reach_when_a_yaw_rate_edge_came_inside_the_widest_it_held() -> None:
    """The slowing MPC's switch: off while the edges are what they were (the paper's case, with change detection or
    without), on once the left edge was learned again at 60 % of its reach, and off again when it is back."""
    for adapt in (True, False):
        s = _learned(adapt)
        assert not s.limits.turn_lost()
        for _ in range(40):  # the same reach again and again: nothing lost
            s.add([0.2, LB.w[1]], [0.2, LB.w[1]])
        assert not s.limits.turn_lost()
    s = _learned()
    _left_turn_cut(s)
    assert s.limits.turn_lost()
    for _ in range(3):  # the reach is back
        s.add([0.2, LB.w[1]], [0.2, LB.w[1]])
    assert s.limits.relearned == 2 and not s.limits.turn_lost()
    # the paper's store: its mean of every boundary pair, once 20 pairs at the lock turned 60 %, lost reach too
    paper = _learned(adapt=False)
    for _ in range(20):
        paper.add([0.2, 0.6 * LB.w[1]], [0.2, LB.w[1]])
    assert paper.limits.turn_lost()


def test_the_mpc_slows_for_bends_only_when_told_the_limits_need_it() -> None:
    """``slow_for_bends`` False gives the references of the paper's MPC (``curve_margin`` 0) whatever the margin;
    True, slower ones before a bend the yaw-rate bound cannot turn at the top speed."""
    from transfer.domain import Bounds
    from transfer.teacher.mpc import MpcConfig, MpcTeacher

    pts = np.array([[0.0, 0.0], [1.0, 0.0]] + [[1.0 + np.sin(a), 1.0 - np.cos(a)] for a in np.linspace(0.1, 3.0, 30)])
    path = Polyline(pts)
    limits = Bounds((0.05, 0.6), (-0.2, 0.2))  # a 1 m bend turns 0.6 rad/s at 0.6 m/s: out of reach
    x = np.array([0.5, 0.0, 0.0])
    paper = MpcTeacher(MpcConfig(solver="ipopt", curve_margin=0.0)).solve(x, path, limits)
    slowing = MpcTeacher(MpcConfig(solver="ipopt", curve_margin=0.9))
    same = slowing.solve(x, path, limits, slow_for_bends=False)
    assert np.array_equal(same.refs, paper.refs)
    slowing.reset()
    slow = slowing.solve(x, path, limits, slow_for_bends=True)
    step = lambda r: np.hypot(*np.diff(r[:, :2], axis=0).T).max()  # noqa: E731
    assert step(slow.refs) < 0.9 * step(paper.refs)


def test_the_store_slows_the_mpc_for_bends_once_its_learner_changed_and_never_where_nothing_did() -> None:
    """``PairStore.slows_for_bends``: off on the paper's case (the same pairs again and again, either store), on once a
    learned edge moved (or a cell was re-learned, or a yaw-rate edge lost reach)."""
    for adapt in (True, False):
        s = _learned(adapt)
        for _ in range(3):
            for lcmd in calibration_commands(LB, 5):
                s.add(lcmd, lcmd)
        assert not s.slows_for_bends() and s.relearned == 0
    s = _learned()
    _left_turn_cut(s)
    assert s.limits.relearned == 1 and s.slows_for_bends()
    cell = _learned()
    centre = calibration_commands(LB, 5)[12]  # the box's centre, a configured cell away from its edges
    for _ in range(20):
        cell.add(centre, centre)
    assert not cell.slows_for_bends()
    for _ in range(12):  # that cell's learner changed by 6 % of the teacher's yaw-rate range (change_tol: 2 %)
        cell.add(centre + [0.0, 0.1], centre)
    assert cell.relearned >= 1 and cell.limits.relearned == 0 and cell.slows_for_bends()
