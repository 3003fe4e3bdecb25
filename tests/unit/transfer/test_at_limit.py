"""``at_limit``: how the guided policy maps a command at a driven learned limit (transfer/policy.py, ``AT_LIMIT``).

The paper's calibrated start (docs/PAPER.md, "The calibrated start"): pairs constructed at the learner's extremes
form well-shaped quadrilaterals up to the limits, so a command there is mapped by its mapping region (``scm``)
just inside the limit, the learner's extreme on the limit's axis; a mission's own pairs along the limit are slivers,
and there the row's interpolation stays (``row``, the default)."""

from __future__ import annotations

import numpy as np
import pytest

from transfer.limits import calibration_commands
from transfer.policy import AT_LIMIT, make_policy
from transfer.store import PairStore


def _calibrated():
    """The paper's cubic learner (the MPC case) after ``scmbridge calibrate``'s 5 x 5 grid (extremes included)."""
    from sim_learner.experiments import mpc_case

    case = mpc_case(False)
    store = PairStore(case.learner_bounds, case.teacher_bounds, k_min=1)
    for u in calibration_commands(case.learner_bounds, 5):
        store.add(case.learner.response(u), u)
    return case, store


def _top_speed_commands(store: PairStore, n: int = 41) -> np.ndarray:
    """Teacher commands at the learned top speed, across the learned yaw-rate range (inside it)."""
    lim, tb = store.limits, store.teacher_bounds
    ws = np.linspace(lim.lo[1], lim.hi[1], n + 2)[1:-1]
    return np.array([tb.denormalise([lim.hi[0], w]) for w in ws])


def test_on_calibrated_pairs_a_command_at_the_limit_is_mapped_by_its_region() -> None:
    case, store = _calibrated()
    lb = case.learner_bounds
    row, region = (make_policy(store, "scm", seed=0, at_limit=a) for a in AT_LIMIT)
    methods = {"row": [], "region": []}
    for t in _top_speed_commands(store):
        a, b = row.map(t, explore=False), region.map(t, explore=False)
        methods["row"].append(a.method)
        methods["region"].append(b.method)
        assert np.all(np.isfinite(b.u_L)) and np.all(b.u_L >= lb.lo) and np.all(b.u_L <= lb.hi)
        assert b.u_L[0] == pytest.approx(lb.hi[0], abs=1e-12)  # the learner's extreme on the limit's axis
        if b.method == "scm":
            assert len(b.region) == 4  # a quadrilateral of calibrated pairs, not the row's two
    assert set(methods["row"]) == {"barycentric"}  # the row, as without calibration
    assert methods["region"].count("scm") >= 0.9 * len(methods["region"])


def test_the_region_maps_the_limit_better_than_the_row_on_calibrated_pairs() -> None:
    # the learner's true yaw rate for each command (its response is known here): the region's yaw rate is nearer
    case, store = _calibrated()
    lb = case.learner_bounds
    errs = {}
    for a in AT_LIMIT:
        policy = make_policy(store, "scm", seed=0, at_limit=a)
        e = []
        for t in _top_speed_commands(store):
            u = policy.map(t, explore=False).u_L
            e.append(abs(case.learner.response(u)[1] - t[1]) / (lb.hi[1] - lb.lo[1]))
        errs[a] = float(np.median(e))
    assert errs["region"] < errs["row"], errs


def test_without_a_region_inside_the_limit_the_row_decides() -> None:
    # pairs only in a strip along the top speed, thinner than the inset: no mapping region just inside the limit
    from sim_learner.experiments import mpc_case

    case = mpc_case(False)
    store = PairStore(case.learner_bounds, case.teacher_bounds, k_min=1)
    lb = case.learner_bounds
    for v in (1.0, 0.997):
        for j in range(11):
            u = lb.denormalise(np.array([v, (j + 0.5) / 11]))
            store.add(case.learner.response(u), u)
    row, region = (make_policy(store, "scm", seed=0, at_limit=a) for a in AT_LIMIT)
    for t in _top_speed_commands(store, 11):
        a, b = row.map(t, explore=False), region.map(t, explore=False)
        assert a.method == b.method and np.array_equal(a.u_L, b.u_L) and a.region == b.region


def test_at_a_corner_of_the_limits_the_region_maps_to_the_learners_corner() -> None:
    # a bounded MPC turning in place at the slowest speed, or hardest at the top speed, sits at two limits at once.
    # The limits are the envelope of the boundary responses; a corner cell's refined pair is the mean of its
    # responses (here two, 0.3 % apart), so the corner itself lies just outside the calibrated region: it is still
    # the region's (both axes moved inside), at the learner's extreme on both
    from sim_learner.experiments import mpc_case

    case = mpc_case(False)
    lb = case.learner_bounds
    store = PairStore(lb, case.teacher_bounds, k_min=1)
    for u in calibration_commands(lb, 5):
        r = case.learner.response(u)
        for s in (1.003, 0.997) if np.all((u == lb.lo) | (u == lb.hi)) else (1.0,):
            store.add(r * s, u)
    lim, tb = store.limits, store.teacher_bounds
    policy = make_policy(store, "scm", seed=0, at_limit="region")
    for iv, iw in ((0, 0), (0, 1), (1, 0), (1, 1)):
        corner = np.array([(lim.lo, lim.hi)[iv][0], (lim.lo, lim.hi)[iw][1]])
        got = policy.map(tb.denormalise(corner), explore=False)
        assert got.method == "scm" and len(got.region) == 4, (corner, got)
        assert np.array_equal(got.u_L, [(lb.lo, lb.hi)[iv][0], (lb.lo, lb.hi)[iw][1]]), (corner, got)


def test_an_unknown_at_limit_is_refused() -> None:
    _, store = _calibrated()
    with pytest.raises(ValueError, match="at_limit"):
        make_policy(store, "scm", seed=0, at_limit="edge")
