"""transfer/limits.py: the learner's limits on the teacher's domain (paper Section 4.2, Eq. learn_capability).

The calibrated box and the online rules (proportional extrapolation, boundary pairs averaged) are tested through the
pair store in tests/unit/transfer/test_step.py, the shrinking of a limit after a change of the learner in
tests/unit/transfer/test_store.py; here ``calibration_commands`` and ``LearnerLimits``' own API directly: what
``update`` returns and counts, the collapsed-box guard, the hull and its fallback, ``forget`` and ``contains``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.domain import Bounds
from transfer.limits import LearnerLimits, calibration_commands
from transfer.store import PairStore

TB = Bounds((0.0, 2.0), (-1.0, 1.0))
LB = Bounds((0.0, 1.0), (-0.5, 0.5))


def _limits() -> LearnerLimits:
    return LearnerLimits(TB, LB, (11, 11), 1e-6)


def test_calibration_commands_span_the_box_with_its_extremes() -> None:
    g = calibration_commands(LB, 3)
    assert g.shape == (9, 2)
    for corner in LB.corners():
        assert any(np.allclose(corner, u) for u in g)
    assert np.all(LB.contains(g))
    assert sorted(set(g[:, 0])) == [0.0, 0.5, 1.0] and sorted(set(g[:, 1])) == [-0.5, 0.0, 0.5]
    g = calibration_commands(LB, (2, 4))
    assert g.shape == (8, 2) and len(set(g[:, 0])) == 2 and len(set(g[:, 1])) == 4
    for bad in (1, (2, 1), (0, 3)):
        with pytest.raises(ValueError, match="a calibration grid needs n >= 2 on each axis"):
            calibration_commands(LB, bad)


def test_before_any_pair_the_limits_are_the_teachers_range() -> None:
    lim = _limits()
    assert lim.box == TB and lim.version == 0
    np.testing.assert_array_equal(lim.hull, TB.corners())
    assert lim.contains([1.9, 0.9]) and not lim.contains([2.1, 0.0])


def test_update_says_whether_the_limits_moved_and_counts_versions() -> None:
    lim = _limits()
    # a learner that behaves as the teacher inside: the proportional bound is the teacher's own: nothing moves
    assert lim.update(np.array([0.5, 0.5]), np.array([0.5, 0.5]), (5, 5)) is False
    assert lim.version == 0
    # a pair on the learner's top speed marks the bound itself
    assert lim.update(np.array([0.8, 0.5]), np.array([1.0, 0.5]), (10, 5)) is True
    assert lim.version == 1 and lim.hi[0] == pytest.approx(0.8)
    assert lim.box.v == pytest.approx((0.0, 1.6))
    # the same boundary pair again: the bound stays (the mean of equal pairs) but the boundary set grew
    assert lim.update(np.array([0.8, 0.5]), np.array([1.0, 0.5]), (10, 5)) is False
    assert lim.version == 2 and lim.bcnt_hi[0] == 2


def test_bounds_that_meet_keep_a_box_of_positive_width() -> None:
    lim = _limits()
    lim.update(np.array([0.3, 0.5]), np.array([1.0, 0.5]), (10, 5))  # top speed at 0.3
    lim.update(np.array([0.6, 0.5]), np.array([0.0, 0.5]), (0, 5))  # lowest speed at 0.6: above the top
    assert lim.hi[0] - lim.lo[0] == pytest.approx(1e-6)
    assert 0.5 * (lim.hi[0] + lim.lo[0]) == pytest.approx(0.45)
    b = lim.box  # still a valid Bounds (min < max)
    assert b.v[0] < b.v[1]


def test_the_hull_encloses_the_boundary_pairs_and_the_refined_pairs() -> None:
    lim = _limits()
    for t, l, cell in (([0.9, 0.5], [1.0, 0.5], (10, 5)), ([0.5, 0.1], [0.5, 0.0], (5, 0)),
                       ([0.5, 0.9], [0.5, 1.0], (5, 10))):
        lim.update(np.array(t), np.array(l), cell)
    hull = lim.hull
    assert hull.shape == (3, 2)
    np.testing.assert_allclose(sorted(map(tuple, hull)), sorted(map(tuple, TB.denormalise(
        [[0.9, 0.5], [0.5, 0.1], [0.5, 0.9]]))))
    assert lim.contains([1.2, 0.0], use_hull=True) and not lim.contains([0.2, 0.0], use_hull=True)
    refined = np.array([[0.1, 0.5]])
    lim.refined_points = lambda: refined
    assert len(lim.hull) == 3  # cached until told the refined pairs changed
    lim.refined_changed()
    assert len(lim.hull) == 4 and lim.contains([0.4, 0.0], use_hull=True)
    got = lim.contains(np.array([[0.4, 0.0], [1.9, 0.9], [1.0, 0.0]]), use_hull=True)
    assert isinstance(got, np.ndarray) and got.tolist() == [True, False, True]


def test_collinear_points_give_the_box_as_the_hull() -> None:
    lim = _limits()
    for w, cell in ((0.2, (10, 2)), (0.5, (10, 5)), (0.8, (10, 8))):  # three pairs on the top-speed line
        lim.update(np.array([0.8, w]), np.array([1.0, w]), cell)
    np.testing.assert_array_equal(lim.hull, lim.box.corners())


def test_forget_replaces_a_cells_boundary_pairs_by_those_since_the_change() -> None:
    lim = _limits()
    for _ in range(3):
        lim.update(np.array([0.8, 0.5]), np.array([1.0, 0.5]), (10, 5))
    v = lim.version
    old_L = np.array([[1.0, 0.5]] * 3)
    lim.forget((10, 5), np.array([[0.8, 0.5]] * 3), old_L, np.array([[0.6, 0.5]]), np.array([[1.0, 0.5]]))
    assert lim.hi[0] == pytest.approx(0.6) and lim.bcnt_hi[0] == 1  # the limit shrank
    assert lim.version == v + 1
    np.testing.assert_allclose(lim.hull_sum[10, 5], [0.6, 0.5])
    assert lim.hull_cnt[10, 5] == 1
    # nothing on the boundary since the change: the cell gives no boundary pair and no hull point any more
    lim.forget((10, 5), np.array([[0.6, 0.5]]), np.array([[1.0, 0.5]]), np.zeros((0, 2)), np.zeros((0, 2)))
    assert lim.bcnt_hi[0] == 0 and lim.hull_cnt[10, 5] == 0


# the SITL finding (docs/BENCHMARKS.md, "The transfer on SITL"): the stock rover's yaw-rate range (120 deg/s) is wider
# than the teacher's (45 deg/s), so the teacher's top yaw rate lies part-way up the learner's range
TEACHER_SITL = Bounds((0.0, 0.6), (-math.pi / 4, math.pi / 4))
LEARNER_WIDE = Bounds((0.0, 1.0), (-math.radians(120.0), math.radians(120.0)))


@pytest.mark.parametrize("overshoot", [0.0, 0.02])
def test_a_pair_at_the_teachers_top_yaw_rate_does_not_set_the_lower_yaw_rate_limit(overshoot: float) -> None:
    store = PairStore(LEARNER_WIDE, TEACHER_SITL)
    w_top = TEACHER_SITL.w[1]
    # the teacher's top yaw rate sent directly, followed exactly (or a little beyond: the teacher part is measured)
    store.add([0.3, w_top * (1.0 + overshoot)], [0.3, w_top])
    box = store.limits.box
    # it says the learner reaches the teacher's top (the upper limit stays the teacher's) and nothing about turning
    # the other way: the lower limit stays the teacher's bottom (it was the teacher's top: [0.785, 0.785])
    assert box.w == pytest.approx(TEACHER_SITL.w)
    assert store.limits.contains([0.3, -0.5]) and store.limits.contains([0.3, 0.0])


def test_a_pair_at_the_teachers_bottom_yaw_rate_does_not_set_the_upper_yaw_rate_limit() -> None:
    store = PairStore(LEARNER_WIDE, TEACHER_SITL)
    w_bot = TEACHER_SITL.w[0]
    store.add([0.3, w_bot * 1.02], [0.3, w_bot])
    assert store.limits.box.w == pytest.approx(TEACHER_SITL.w)


def test_a_pair_inside_the_teachers_range_still_extrapolates_both_sides() -> None:
    # the paper's rule where it holds (Eq. learn_capability and its mirror): unchanged by the edge rule above
    lim = _limits()
    lim.update(np.array([0.5, 0.9]), np.array([0.5, 0.75]), (5, 8))
    assert lim.lo[1] == pytest.approx(1.0 - 0.1 / 0.25)
    lim = _limits()
    lim.update(np.array([0.1, 0.5]), np.array([0.25, 0.5]), (2, 5))
    assert lim.hi[0] == pytest.approx(0.4)  # a convex learner's low pair underestimates: the probe measures it


def test_after_a_pair_at_the_teachers_top_a_straight_pair_sets_the_lower_limit_by_the_mirror() -> None:
    store = PairStore(LEARNER_WIDE, TEACHER_SITL)
    store.add([0.3, TEACHER_SITL.w[1]], [0.3, TEACHER_SITL.w[1]])
    store.add([0.3, 0.0], [0.3, 0.0])  # straight ahead: the learner's middle gives the teacher's middle
    assert store.limits.box.w == pytest.approx(TEACHER_SITL.w)


def test_with_a_memory_a_bound_follows_its_boundary_pairs_and_without_it_every_pair_weighs_alike() -> None:
    """A learner that lost a third of its top speed: 100 boundary pairs at the old top, then 20 at the new one. With
    a memory of 20 pairs (the store's with change detection, k_min 5) the bound has moved 1 - (19/20)^20 = 64 % of the
    way to the new top; the paper's mean of every pair a sixth. Before the change both are the old top."""
    old, new = 0.9, 0.6
    cell = (10, 5)
    for memory in (0, 20):
        lim = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=memory)
        for k in range(100):
            lim.update(np.array([old + 0.01 * (-1) ** k, 0.5]), np.array([1.0, 0.5]), cell)
        assert lim.hi[0] == pytest.approx(old, abs=0.002)  # the alternating noise, weighed by recency or not
        for _ in range(20):
            lim.update(np.array([new, 0.5]), np.array([1.0, 0.5]), cell)
        moved = (old - lim.hi[0]) / (old - new)
        if memory:
            assert moved == pytest.approx(1 - (19 / 20) ** 20, abs=0.01) and lim.bcnt_hi[0] == 20
        else:
            assert moved == pytest.approx(20 / 120, abs=0.01) and lim.bcnt_hi[0] == 120
    with pytest.raises(ValueError, match="memory"):
        LearnerLimits(TB, LB, (11, 11), 1e-6, memory=1)
    assert PairStore(LB, TB, adapt=True).limits.memory == 20 and PairStore(LB, TB).limits.memory == 0


def _full_lock(lim: LearnerLimits, v: float, w: float, side: int = 1) -> bool:
    """One pair at the learner's yaw-rate edge (side 1: the upper; 0: the lower) whose motion was (v, w), teacher
    units."""
    t_n = TB.normalise(np.array([v, w]))
    l_n = np.array([0.5, 1.0 if side else 0.0])
    return lim.update(t_n, l_n, (5, 10 if side else 0))


def test_a_learner_that_cannot_turn_in_place_learns_its_curvature_per_side() -> None:
    """``needs_speed``: each yaw-rate side's bound is the least-squares slope through standstill of its full-lock
    pairs; the box's yaw-rate edge is that slope times the box's top speed, and a side with no pair is unbounded
    (infinite) and keeps the box's rule. A learner that turns in place has no curvature bound but still keeps the
    sums (``pairs show`` prints them)."""
    lim = LearnerLimits(TB, LB, (11, 11), 1e-6, needs_speed=True)
    assert lim.curvature == (-math.inf, math.inf)
    for v in (0.2, 0.5, 1.0, 1.6):
        _full_lock(lim, v, 0.5 * v)
    k_lo, k_hi = lim.curvature
    assert k_lo == -math.inf and k_hi == pytest.approx(0.5)
    assert lim.known_curvature() == (None, pytest.approx(0.5))  # not learned is None, as reports carry it
    assert lim.box.w[1] == pytest.approx(0.5 * lim.box.v[1])  # the box's top speed is the teacher's (2.0): 1.0
    assert lim.box.w[0] == TB.w[0]
    # the upper edge at a speed is that speed's share of the turn; the lower one, unknown, is the box's
    lo, hi = lim.turn_edges_at(float(TB.normalise(np.array([0.4, 0.0]))[0]))
    assert TB.denormalise(np.array([0.0, hi]))[1] == pytest.approx(0.2)
    assert lo == pytest.approx(lim.lo[1])
    for v in (0.4, 1.2):
        _full_lock(lim, v, -0.3 * v, side=0)
    assert lim.curvature[0] == pytest.approx(-0.3)
    assert lim.box.w[0] == pytest.approx(-0.3 * lim.box.v[1])
    # a turn read the wrong way (part-way out of a turn the other way) cannot forbid driving straight
    bad = LearnerLimits(TB, LB, (11, 11), 1e-6, needs_speed=True)
    _full_lock(bad, 0.5, -0.05)
    assert bad.curvature[1] == 0.0 and bad.box.w[1] >= 0.0
    # a learner that turns in place: no bound, the same sums
    skid = LearnerLimits(TB, LB, (11, 11), 1e-6)
    for v in (0.2, 0.5, 1.0, 1.6):
        _full_lock(skid, v, 0.5 * v)
    assert skid.curvature is None and skid.learned_curvature()[1] == pytest.approx(0.5)
    assert skid.known_curvature() == (None, pytest.approx(0.5))  # learned whatever the learner turns like
    assert skid.box.w[1] == pytest.approx(np.mean([0.1, 0.25, 0.5, 0.8]))  # the mean of its boundary pairs
    skid.set_needs_speed(True)
    assert skid.box.w[1] == pytest.approx(0.5 * skid.box.v[1])
    skid.set_needs_speed(False)
    assert skid.box.w[1] == pytest.approx(np.mean([0.1, 0.25, 0.5, 0.8]))


def test_a_learned_curvature_follows_a_change_with_a_memory_and_forgets_with_its_cell() -> None:
    """With a ``memory`` the curvature is recency-weighted, so a rover whose steering lost reach is followed by its
    full-lock pairs alone; ``forget`` of a cell on the yaw-rate edge keeps only its pairs since the change."""
    lim = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=8, needs_speed=True)
    for _ in range(50):
        _full_lock(lim, 1.0, 0.8)
    for _ in range(30):
        _full_lock(lim, 1.0, 0.4)
    assert lim.curvature[1] == pytest.approx(0.4, abs=0.01)
    never = LearnerLimits(TB, LB, (11, 11), 1e-6, needs_speed=True)
    for w in [0.8] * 50 + [0.4] * 30:
        _full_lock(never, 1.0, w)
    assert never.curvature[1] == pytest.approx((50 * 0.8 + 30 * 0.4) / 80)
    old_T, old_L = TB.normalise(np.array([[1.0, 0.8]] * 3)), np.array([[0.5, 1.0]] * 3)
    new_T, new_L = TB.normalise(np.array([[1.0, 0.3]] * 2)), np.array([[0.5, 1.0]] * 2)
    never.forget((5, 10), old_T, old_L, new_T, new_L)
    assert never.curvature[1] == pytest.approx(0.3)
    assert never.box.w[1] == pytest.approx(0.3 * never.box.v[1])


def test_before_a_full_lock_pair_a_curvature_is_extrapolated_from_the_outliers() -> None:
    """Eq. learn_capability read as a curvature: a pair commanded at a share of the full lock, the first beyond
    every earlier one on its side, gives (omega / v) / share until a full-lock pair arrives; too slow a pair or too
    small a share gives nothing, and the full-lock pairs then decide."""
    lim = LearnerLimits(TB, LB, (11, 11), 1e-6, needs_speed=True)
    t_n = TB.normalise(np.array([1.0, 0.3]))  # omega / v = 0.3, commanded at 60 % of the lock (0.3 of 0.5)
    lim.update(t_n, LB.normalise(np.array([0.5, 0.3])), (5, 8))
    assert lim.curvature[1] == pytest.approx(0.5) and math.isinf(lim.curvature[0])
    assert lim.box.w[1] == pytest.approx(0.5 * lim.box.v[1])
    lim.update(TB.normalise(np.array([0.1, 0.05])), LB.normalise(np.array([0.05, 0.4])), (0, 9))  # too slow
    assert lim.curvature[1] == pytest.approx(0.5)
    lim.update(TB.normalise(np.array([1.0, -0.02])), LB.normalise(np.array([0.5, -0.05])), (5, 4))  # too small
    assert math.isinf(lim.curvature[0])
    _full_lock(lim, 1.0, 0.4)
    assert lim.curvature[1] == pytest.approx(0.4)


def test_the_first_pair_of_a_run_extrapolates_the_curvature_of_the_side_it_turns_to_either_way() -> None:
    """The first pair is a new outlier on both sides of the yaw rate; it extrapolates the side its turn is on. Found
    on SITL's Ackermann rover: a run whose first settled pair was a right turn was read as the left side's outlier,
    which a right turn cannot extrapolate, and the right side's curvature was never learned (its later pairs were
    not beyond that first one)."""
    for sign, side in ((-1.0, 0), (1.0, 1)):
        lim = LearnerLimits(TB, LB, (11, 11), 1e-6, needs_speed=True)
        lim.update(TB.normalise(np.array([1.0, sign * 0.3])), LB.normalise(np.array([0.5, sign * 0.3])), (5, 5))
        assert lim.curvature[side] == pytest.approx(sign * 0.5)  # (omega / v) / share of the lock (0.3 of 0.5)
        assert math.isinf(lim.curvature[1 - side])
        # the same turn again is no new outlier: the side keeps what it has
        lim.update(TB.normalise(np.array([1.0, sign * 0.29])), LB.normalise(np.array([0.5, sign * 0.3])), (5, 5))
        assert lim.curvature[side] == pytest.approx(sign * 0.5)


def _edge_pair(lim: LearnerLimits, w: float, v: float = 1.0, side: int = 1) -> None:
    """One pair at the learner's yaw-rate edge whose motion was (v, w), teacher units, in its cell (5, 10) or (5, 0)."""
    lim.update(TB.normalise(np.array([v, w])), np.array([0.5, 1.0 if side else 0.0]), (5, 10 if side else 0))


def test_an_edge_that_moved_is_learned_again_from_its_recent_boundary_pairs_and_noise_alone_never_moves_it() -> None:
    """The edges' change test (``set_change_test``, the store's with change detection): a steering that lost 40 % of
    its reach (a turn-rate cap lowered mid-run) after 12 boundary pairs. The residuals' mean is beyond 2 % of the
    teacher's range from the first pair after the change, but one pair beyond is an outlier (one outlier of that size
    before the change moves nothing); the second alarms, and the edge keeps the recent pairs that agree with the
    change (the outlier among them): the new reach. With the memory alone the edge is the mean of its 15 pairs, 4 of
    them at the new reach (the paper's mean of every pair the same: fewer pairs than the memory). Noise alone (1.5 %
    of the range, 4000 pairs) never alarms; the hull's point of the side's cell follows the edge."""
    rng = np.random.default_rng(3)
    old, new = 0.6, 0.36
    for test in (True, False):
        lim = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=20)
        if test:
            lim.set_change_test(5, 0.02)
        for k in range(12):
            _edge_pair(lim, (new if k == 8 else old) + 0.01 * (-1) ** k)  # the ninth an outlier
        assert lim.relearned == 0 and lim.box.w[1] == pytest.approx(old - 0.02, abs=0.002)
        _edge_pair(lim, new)
        assert lim.relearned == 0  # one pair beyond: not yet
        _edge_pair(lim, new)
        _edge_pair(lim, new)
        if test:
            # the recent pairs that agree with the change: the outlier too, the three after the change
            assert lim.relearned == 1 and lim.bcnt_hi[1] == 4
            assert lim.box.w[1] == pytest.approx(new + 0.0025, abs=1e-9)
            hull_w = (lim.hull_sum[5, 10] / lim.hull_cnt[5, 10])[1]
            assert TB.denormalise(np.array([0.5, hull_w]))[1] == pytest.approx(new + 0.0025)
        else:
            assert lim.relearned == 0 and (old - lim.box.w[1]) / (old - new) == pytest.approx(4 / 15, abs=0.01)
    quiet = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=20)
    quiet.set_change_test(5, 0.02)
    for _ in range(2000):
        _edge_pair(quiet, old + 0.03 * rng.standard_normal())
        _edge_pair(quiet, -old + 0.03 * rng.standard_normal(), side=0)
    assert quiet.relearned == 0 and quiet.box.w[1] == pytest.approx(old, abs=0.02)


def test_each_sides_change_is_found_on_its_second_pair_with_few_pairs_at_the_locks_before() -> None:
    """The SITL rover's turn-rate cut, as its pairs came (traced): each side at its lock three times before (the start's
    turn on the spot, the first bend), then both sides' reach cut, the lower side's met first. Each side's change is
    found on its second pair after it: the noise takes a difference from each side's second pair on. From its third,
    the six pairs gave two differences, and the test, which waits for k = 5, let the lower side's second pair pass
    (a run on CI, 2026-11-28, ended with a side between its old and new reach)."""
    lim = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=20)
    lim.set_change_test(5, 0.02)
    old, new = 0.38, 0.235  # the rover's 0.30 and 0.185 rad/s on a teacher range of +-0.785: 7 % of the range
    for k in range(3):
        _edge_pair(lim, old + 0.0005 * (-1) ** k)
    for k in range(3):
        _edge_pair(lim, -old + 0.0005 * (-1) ** k, side=0)
    for side in (0, 1):
        w = new if side else -new
        _edge_pair(lim, w, side=side)
        assert lim.relearned == side  # one pair beyond: not yet
        _edge_pair(lim, w, side=side)
        assert lim.relearned == side + 1 and lim.box.w[side] == pytest.approx(w)
        _edge_pair(lim, w, side=side)
    assert lim.relearned == 2


def test_the_noise_is_not_raised_by_a_change_its_edge_takes_in() -> None:
    """The upper side at its lock three times, the lower side once; then the lower side's reach is cut and its edge,
    the mean of its pairs, takes four new pairs in (their residuals against it shrink: 7.2, 3.6, 2.4, 1.8 % of the
    range); then the upper side's reach is cut: found on its second pair. Against the edge each pair was taken at,
    the lower side's shrinking residuals' differences would be parts of its change, half of the noise's sample, and
    hide the upper side's change; against one edge a change is one difference."""
    lim = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=20)
    lim.set_change_test(5, 0.02)
    old, new = 0.38, 0.235
    for k in range(3):
        _edge_pair(lim, old + 0.0005 * (-1) ** k)
    _edge_pair(lim, -old, side=0)
    for _ in range(4):
        _edge_pair(lim, -new, side=0)
    assert lim.relearned == 0 and lim.box.w[0] == pytest.approx(-(old + 4 * new) / 5)
    _edge_pair(lim, new)
    assert lim.relearned == 0
    _edge_pair(lim, new)
    assert lim.relearned == 1 and lim.box.w[1] == pytest.approx(new)


def test_a_curvature_that_moved_is_learned_again_at_whatever_speed_its_pairs_come() -> None:
    """``needs_speed``: a yaw-rate side's residual is against its curvature at the pair's own speed, so full-lock pairs
    at several speeds are no change, and a rover whose steering lost reach is found by a few of them: its curvature
    is then its recent pairs'."""
    lim = LearnerLimits(TB, LB, (11, 11), 1e-6, memory=20, needs_speed=True)
    lim.set_change_test(5, 0.02)
    speeds = [0.4, 0.8, 1.2, 1.6]
    for k in range(16):
        _edge_pair(lim, 0.5 * speeds[k % 4], v=speeds[k % 4])
    assert lim.relearned == 0 and lim.curvature[1] == pytest.approx(0.5)
    for k in range(4):
        _edge_pair(lim, 0.3 * speeds[k % 4], v=speeds[k % 4])
    assert lim.relearned == 1 and lim.curvature[1] == pytest.approx(0.3)
    assert lim.box.w[1] == pytest.approx(0.3 * lim.box.v[1])
