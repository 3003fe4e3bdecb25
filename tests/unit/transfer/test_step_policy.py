"""The transfer policies (transfer/policy.py) as the transfer step uses them: the paper policy's fall-backs, probes of
limits never driven, the guided policy's estimate, offset, exploration and its promise never to perturb when told
not to, and a finite command inside the learner's box whatever is asked."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.boxes import LB, TB, affine_store
from transfer.pairs import teacher_equivalent
from transfer.policy import GuidedPolicy, make_policy
from transfer.store import PairStore
from transfer.teacher.unicycle import step


# ------------------------------------------------------------------------------------------------- policy
def test_paper_policy_falls_back_exactly_as_specified() -> None:
    s = PairStore(LB, TB, k_min=2)
    p = make_policy(s, "scm", rng=np.random.default_rng(3), exploration="paper")
    uT = np.array([0.2, 0.05])
    m = p.map(uT)  # nothing learned: direct, the teacher command clipped into the learner's box
    assert m.method == "direct" and np.allclose(m.u_L, LB.clip(uT))
    far = np.array([0.55, 0.7])
    assert np.allclose(p.map(far).u_L, LB.clip(far))
    # measure the learner's limits first (its four extreme commands), so no limit is probed below
    for corner in LB.corners():
        s.add(corner, corner)
    # configure the cell of uT: no region yet (one pair), so the policy perturbs into a neighbouring empty cell
    for _ in range(2):
        s.add([0.1, 0.0], uT)
    cell = s.cell_of(uT)
    m = p.map(uT)
    assert m.method == "perturb"
    c2 = s.cell_of(m.u_L)
    assert max(abs(c2[0] - cell[0]), abs(c2[1] - cell[1])) == 1 and not s.is_configured(c2)
    # told not to explore (near an obstacle), it maps without perturbing, as the guided policy does
    calm = p.map(uT, explore=False, plan=[[0.3, 0.1]])
    assert calm.method != "perturb"
    assert np.array_equal(calm.u_L, make_policy(s, "scm", seed=0).map(uT, explore=False).u_L)
    # seeded: the same sequence for the same seed
    q1 = make_policy(s, "scm", rng=np.random.default_rng(9), exploration="paper")
    q2 = make_policy(s, "scm", rng=np.random.default_rng(9), exploration="paper")
    assert all(np.array_equal(q1.map(uT).u_L, q2.map(uT).u_L) for _ in range(5))
    # the baseline applies the teacher command directly, always
    base = make_policy(s, "identity")
    assert base.map(uT).method == "direct"
    with pytest.raises(ValueError, match="finite"):
        p.map([np.nan, 0.0])
    with pytest.raises(ValueError, match="exploration"):
        make_policy(s, "scm", exploration="random")


@pytest.mark.parametrize("exploration", ["paper", "guided"])
def test_policy_probes_a_limit_whose_learner_boundary_was_never_driven(exploration: str) -> None:
    s = PairStore(LB, TB, k_min=5)
    s.add(TB.denormalise([0.1, 0.5]), LB.denormalise([0.5, 0.5]))  # interior outlier: proportional estimate
    p = make_policy(s, "scm", seed=0, exploration=exploration)
    box = s.limits.box
    m = p.map([box.v[1], 0.0])  # the teacher saturates at the estimated top speed
    assert m.method == "perturb" and m.u_L[0] == LB.v[1]  # the learner's top speed is driven once
    x0 = np.zeros(3)
    s.add(teacher_equivalent(x0, step(x0, [0.3, m.u_L[1]], 0.1), 0.1), m.u_L)  # the learner really does 0.3
    assert s.limits.box.v[1] == pytest.approx(0.3)  # measured, not extrapolated


def _square_store() -> PairStore:
    """Four refined pairs (k_min = 1) at the centres of learner cells (4..5, 4..5); the learner moves like the
    teacher in normalised units, so the teacher hull is the square [4.5, 5.5]^2 / 11 and the map is the identity
    there. The proportional limit estimates are the teacher's own range, so only its extremes would be probed."""
    s = PairStore(LB, TB, k_min=1)
    for i in (4, 5):
        for j in (4, 5):
            n = (np.array([i, j]) + 0.5) / 11
            s.add(TB.denormalise(n), LB.denormalise(n))
    return s


def _n(cells: tuple[float, float]) -> np.ndarray:
    """Normalised coordinates from grid-cell units."""
    return np.asarray(cells, dtype=float) / 11


def test_guided_policy_without_pairs_and_without_a_region_applies_the_estimate() -> None:
    s = PairStore(LB, TB, k_min=2)
    p = make_policy(s, "scm", seed=0)
    assert isinstance(p, GuidedPolicy)  # the default
    uT = np.array([0.2, 0.05])
    m = p.map(uT)  # nothing learned: as in the paper, the teacher command read as a learner command, clipped
    assert m.method == "direct" and np.allclose(m.u_L, LB.clip(uT))
    # inside a triangle whose only neighbours are missing (three pairs: no quadrilateral, so no SC region),
    # the guided policy interpolates that triangle instead of exploring around a command the pairs enclose
    tri = PairStore(LB, TB, k_min=1)
    for c in [(2.5, 2.5), (8.5, 2.5), (2.5, 8.5)]:
        tri.add(TB.denormalise(_n(c)), LB.denormalise(_n(c)))
    t = TB.denormalise(_n((4.0, 4.0)))
    assert make_policy(tri, "scm", seed=0).mapper.map_normalised(_n((4.0, 4.0))) is None
    g = make_policy(tri, "scm", seed=0).map(t)
    assert g.method == "barycentric" and np.allclose(g.u_L, LB.denormalise(_n((4.0, 4.0))), atol=1e-12)
    assert make_policy(tri, "scm", seed=0, exploration="paper").map(t).method != "scm"


def test_guided_policy_applies_the_offset_from_the_region_directly_and_continuously() -> None:
    s = _square_store()
    p = make_policy(s, "scm", seed=0, choice=False)
    # 0.02 (normalised teacher units) right of the square's edge: within ``saturate``, no exploring; the map of
    # the nearest edge point plus the offset read one-to-one in physical units
    t_n = _n((5.5, 4.8)) + np.array([0.02, 0.0])
    m = p.map(TB.denormalise(t_n))
    want = _n((5.5, 4.8)) + np.array([0.02, 0.0]) * TB.span / LB.span
    assert m.method == "direct" and np.allclose(m.u_L, LB.denormalise(want), atol=1e-7)
    assert len(m.region) == 3  # the triangle of the edge point it is anchored on
    # at the edge it joins the SC map of the region (continuous, no jump between the two)
    inside = p.map(TB.denormalise(_n((5.5, 4.8)) - np.array([1e-7, 0.0])))
    edge = p.map(TB.denormalise(_n((5.5, 4.8)) + np.array([1e-7, 0.0])))
    assert inside.method == "scm" and edge.method == "direct"
    assert np.allclose(inside.u_L, edge.u_L, atol=1e-6 * float(LB.span.max()))


def test_guided_policy_explores_the_neighbour_that_serves_the_plan_at_the_least_detour() -> None:
    s = _square_store()
    p = make_policy(s, "scm", seed=0, saturate=0.01)
    # 0.02 right of the square: beyond ``saturate`` now, and the estimate (5.98, 4.8 in cell units) lies in the
    # configured cell (5, 4): explore a neighbour
    t = TB.denormalise(_n((5.5, 4.8)) + np.array([0.02, 0.0]))
    est = _n((5.5, 4.8)) + np.array([0.02, 0.0]) * TB.span / LB.span
    m = p.map(t)
    assert m.method == "perturb" and s.cell_of(m.u_L) == (6, 4)  # the empty neighbour nearest to the estimate
    # the nearest point of that cell to the estimate, a tenth of a cell inside it
    np.testing.assert_allclose(LB.normalise(m.u_L), [6.1 / 11, est[1]], atol=1e-12)
    # the plan turns left: its commands map into cell (6, 5) (estimate (6.5, 5.5)): explore that one instead
    plan_t = TB.denormalise(_n((5.5, 5.5)) + np.array([(1 / 11) / (TB.span[0] / LB.span[0]), 0.0]))
    m2 = p.map(t, plan=[plan_t] * 3)
    assert m2.method == "perturb" and s.cell_of(m2.u_L) == (6, 5)
    np.testing.assert_allclose(LB.normalise(m2.u_L), [6.1 / 11, 5.1 / 11], atol=1e-12)
    # deterministic: no tie, so the random generator is not consulted and any seed gives the same command
    assert np.array_equal(make_policy(s, "scm", seed=123, saturate=0.01).map(t).u_L, m.u_L)


def test_guided_policy_never_perturbs_when_told_not_to_explore() -> None:
    rng = np.random.default_rng(4)
    stores = [PairStore(LB, TB, k_min=1), _square_store()]
    lone = PairStore(LB, TB, k_min=1)
    lone.add(TB.denormalise([0.1, 0.5]), LB.denormalise([0.5, 0.5]))  # an unprobed, estimated limit
    stores.append(lone)
    for s in stores:
        p = make_policy(s, "scm", seed=0, saturate=0.01)
        box = s.limits.box
        cmds = [TB.denormalise(rng.random(2)) for _ in range(200)] + [box.hi, box.lo, [box.v[1], 0.0]]
        methods = {p.map(u, explore=False).method for u in cmds}
        assert "perturb" not in methods
        for u in cmds:
            m = p.map(u, explore=False)
            assert np.all(np.isfinite(m.u_L)) and LB.contains(m.u_L)
    # ... while the same policy, allowed to, does explore (probe the limit, perturb next to the square)
    assert make_policy(lone, "scm", seed=0).map([lone.limits.box.v[1], 0.0]).method == "perturb"
    sq = make_policy(stores[1], "scm", seed=0, saturate=0.01)
    assert sq.map(TB.denormalise(_n((5.5, 4.8)) + np.array([0.02, 0.0]))).method == "perturb"


@settings(max_examples=150, deadline=None)
@given(st.floats(-5, 5), st.floats(-5, 5), st.sampled_from(["scm", "barycentric", "affine", "identity"]),
       st.sampled_from(["paper", "guided"]), st.booleans(), st.booleans())
def test_policy_output_is_always_finite_and_inside_the_learner_box(v: float, w: float, mapper: str,
                                                                   exploration: str, explore: bool,
                                                                   with_plan: bool) -> None:
    s, _, _ = affine_store(k_min=1)
    plan = [[v, w], [-v, 2 * w], [np.nan, 0.0]] if with_plan else None
    m = make_policy(s, mapper, seed=1, exploration=exploration).map([v, w], plan=plan, explore=explore)
    assert np.all(np.isfinite(m.u_L)) and LB.contains(m.u_L)
