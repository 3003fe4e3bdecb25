"""transfer/policy.py: the transfer policy (paper Section 5.2), teacher command -> learner command.

Most of its behaviour is tested in tests/unit/transfer/test_step.py (the paper's fallbacks, the probe of a
never-driven limit, the guided estimate, exploration steered by the plan, no perturbation with ``explore=False``, a
finite command inside the learner's box for any input, hole filling). Here the rest of the module's own API:
``planned_commands``, the refusals of the options, the paper policy's saturation rule and its ring-by-ring search,
the plan read lazily, and a mapper given as an object."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.domain import Bounds
from transfer.mappers import AffineMapper, BarycentricMapper
from transfer.policy import (
    EXPLORATIONS,
    POLICIES,
    GuidedPolicy,
    Mapped,
    PaperPolicy,
    make_policy,
    planned_commands,
)
from transfer.store import PairStore
from transfer.teacher.unicycle import step

UNIT = Bounds((0.0, 1.0), (0.0, 1.0))  # teacher and learner alike: normalised = physical


def _store(cells: list[tuple[int, int]]) -> PairStore:
    """k_min = 1, one pair at the centre of each listed cell of the 11 x 11 grid; the learner is the teacher."""
    s = PairStore(UNIT, UNIT, k_min=1)
    for c in cells:
        n = (np.array(c) + 0.5) / 11
        s.add(n, n)
    return s


def test_planned_commands_recovers_the_teachers_inputs_after_the_first() -> None:
    cmds = np.array([[0.3, 0.1], [0.4, -0.2], [0.5, 0.0], [0.2, 0.3], [0.1, 0.1]])
    x = [np.array([1.0, 2.0, 0.5])]
    for u in cmds:
        x.append(step(x[-1], u, 0.1))
    pred = np.array(x)
    np.testing.assert_allclose(planned_commands(pred, 0.1), cmds[1:], atol=1e-12)
    np.testing.assert_allclose(planned_commands(pred, 0.1, k=2), cmds[1:3], atol=1e-12)
    for bad in (pred[:2], pred[:, :2], pred[0], np.where(np.arange(6)[:, None] == 3, np.nan, pred)):
        out = planned_commands(bad, 0.1)  # too short, not poses, one pose, not finite: no plan
        assert out.shape == (0, 2)


def test_unknown_names_and_options_out_of_range_are_refused() -> None:
    s = _store([])
    assert set(POLICIES) == set(EXPLORATIONS)
    with pytest.raises(ValueError, match="unknown exploration 'greedy'; known: paper, guided"):
        make_policy(s, exploration="greedy")
    with pytest.raises(ValueError, match="unknown mapper"):
        make_policy(s, "linear")
    with pytest.raises(ValueError, match=r"inset must be in \[0, 0.5\), got 0.5"):
        make_policy(s, inset=0.5)
    with pytest.raises(ValueError, match=r"fill_budget must be in \[0, 1\), got 1.0"):
        GuidedPolicy(s, fill_budget=1.0)
    with pytest.raises(ValueError, match=r"fill_depth must be in \(0, 1\), got 0.0"):
        GuidedPolicy(s, fill_depth=0.0)
    with pytest.raises(ValueError, match=r"fill_phase must be in \[0, 1\), got 1.0"):
        GuidedPolicy(s, fill_phase=1.0)
    p = make_policy(s, exploration="paper")
    for bad in ([math.inf, 0.0], [0.0, math.nan]):
        with pytest.raises(ValueError, match="teacher command must be finite"):
            p.map(bad)
    with pytest.raises(ValueError):
        p.map([0.1, 0.2, 0.3])  # not one command


def test_mapped_defaults_and_a_mapper_given_as_an_object() -> None:
    m = Mapped(np.zeros(2), "direct")
    assert m.region == () and m.vetoed is False
    s = _store([(4, 4), (4, 5), (5, 4), (5, 5)])
    mapper = BarycentricMapper(s)
    p = make_policy(s, mapper, seed=0)
    assert p.mapper is mapper
    got = p.map([5.0 / 11, 5.0 / 11])
    assert got.method == "barycentric" and got.u_L == pytest.approx([5.0 / 11, 5.0 / 11])


def test_the_paper_policy_maps_a_saturated_command_through_the_nearest_learned_command() -> None:
    s = _store([(4, 4), (4, 5), (5, 4), (5, 5)])  # the identity learned on the square [4.5, 5.5]^2 / 11
    edge = np.array([5.5, 4.8]) / 11
    t = edge + np.array([0.02, 0.0])  # inside the learned limits, 0.02 outside the region: within ``saturate``
    m = PaperPolicy(s, seed=0).map(t)
    assert m.method == "scm" and len(m.region) == 4
    np.testing.assert_allclose(m.u_L, edge, atol=1e-7)  # the nearest point's map: the offset is dropped
    m = PaperPolicy(s, seed=0, saturate=0.01).map(t)  # beyond ``saturate``, in the configured cell (5, 4): explore
    c = s.cell_of(m.u_L)
    assert m.method == "perturb" and not s.is_configured(c) and max(abs(c[0] - 5), abs(c[1] - 4)) == 1


def test_the_paper_policy_searches_ring_by_ring_for_an_unconfigured_cell() -> None:
    s = _store([(0, 0), (0, 1), (1, 0), (1, 1)])  # the corner cell and its whole first ring
    t = np.array([0.2, 0.2]) / 11  # in cell (0, 0), outside the region of cell centres
    p = PaperPolicy(s, seed=0, saturate=0.0)
    seen = set()
    for _ in range(30):
        m = p.map(t)
        assert m.method == "perturb"
        c = s.cell_of(m.u_L)
        assert max(c) == 2 and not s.is_configured(c)  # the second ring, the first holding a free cell
        seen.add(c)
    # in that ring, the free cells nearest to where the affine fit puts t (the identity: t itself, (0.2, 0.2) in
    # cell units) are (0, 2) and (2, 0), equally near: the random generator breaks the tie
    assert seen == {(0, 2), (2, 0)}
    s_full = PairStore(UNIT, UNIT, grid=(2, 2), k_min=1)
    for c in ((0, 0), (0, 1), (1, 0), (1, 1)):
        n = (np.array(c) + 0.5) / 2
        s_full.add(n, n)
    m = PaperPolicy(s_full, seed=0, saturate=0.0).map([0.1, 0.1])  # every cell configured: direct
    assert m.method == "direct" and m.u_L == pytest.approx([0.1, 0.1])


def test_a_plan_given_as_a_function_is_read_only_when_a_cell_is_chosen() -> None:
    s = _store([(4, 4), (4, 5), (5, 4), (5, 5)])
    calls = []

    def plan() -> np.ndarray:
        calls.append(1)
        return np.array([[6.5 / 11, 5.5 / 11]])

    # the paper's SC map alone (choice=False): the choice of map is tests/unit/transfer/test_choice.py's
    p = make_policy(s, seed=0, saturate=0.01, fill_budget=0.0, choice=False)
    assert p.map([5.0 / 11, 5.0 / 11], plan=plan).method == "scm"  # served from the region: no choice made
    assert p.map([5.0 / 11, 5.0 / 11], plan=plan, explore=False).method == "scm"
    assert calls == []
    m = p.map(np.array([5.5, 4.8]) / 11 + np.array([0.02, 0.0]), plan=plan)  # beyond saturate: explores
    assert m.method == "perturb" and calls == [1]
    assert s.cell_of(m.u_L) == (6, 5)  # the neighbour that serves the plan too


def test_unperturbed_many_is_each_rows_own_unperturbed_mapping_and_its_linear_guess_has_the_same_region() -> None:
    """``_unperturbed_many`` (a hole search's rows at once) gives each row what ``_unperturbed`` gives it alone, at a
    learned limit, inside the SC region and outside it (the estimate); ``linear=True`` (the search's ranking, no
    SC map built) is the piecewise-linear map of the same triangles and says "direct" on exactly the same rows."""
    from sim_learner.experiments import mpc_case

    case = mpc_case(False)
    store = PairStore(case.learner_bounds, case.teacher_bounds, k_min=1)
    lb, tb = case.learner_bounds, case.teacher_bounds
    for i in range(11):
        for j in range(11):
            if i < 3 and j < 4:
                continue  # a hole at the slow hard right turns: rows outside the region
            u = lb.denormalise(np.array([(i + 0.5) / 11, (j + 0.5) / 11]))
            store.add(case.learner.response(u), u)
    p = GuidedPolicy(store, "scm", seed=0, choice=False)  # the SC map in the rows (the choice: test_choice.py)
    rng = np.random.default_rng(3)
    ts = tb.denormalise(np.vstack([rng.uniform(-0.05, 1.05, (80, 2)),
                                   [[store.limits.hi[0], 0.5], [store.limits.lo[0], 0.3]]]))
    u, methods = p._unperturbed_many(ts)
    for k, t in enumerate(ts):
        u1, m1, _, _ = p._unperturbed(t, tb.normalise(t))
        assert methods[k] == m1 and u[k].tolist() == u1.tolist(), (t, methods[k], m1)
    assert {"direct", "scm"} <= set(methods)
    lin, lin_methods = p._unperturbed_many(ts, linear=True)
    assert [m == "direct" for m in lin_methods] == [m == "direct" for m in methods]
    assert "scm" not in lin_methods and np.all(lb.contains(lin))
    inside = [k for k, m in enumerate(methods) if m == "scm"]
    assert np.max(np.abs(lb.normalise(lin[inside]) - lb.normalise(u[inside]))) < 0.05  # a guess, and a close one


def test_the_linear_mappers_read_the_sc_mappers_triangulation_and_map_as_their_own_would() -> None:
    """A policy's barycentric fallback and affine fit read its SC mapper's Delaunay triangulation (one build a store
    revision for all three) and give exactly what mappers with a triangulation of their own give, also after the
    store's refined pairs moved."""
    rng = np.random.default_rng(5)
    s = _store([(i, j) for i in range(1, 10, 2) for j in range(0, 11, 3)])
    pol = make_policy(s, "scm", exploration="guided")
    own, fit = BarycentricMapper(s), AffineMapper(s)
    for k in range(3):
        pts = rng.uniform(0.0, 1.0, (40, 2))
        for p in pts:
            a, b = pol._fallback.map_normalised(p), own.map_normalised(p)
            assert (a is None) == (b is None) and (a is None or np.array_equal(a[0], b[0]))
            a, b = pol._fallback.nearest_on_hull(p), own.nearest_on_hull(p)
            assert np.array_equal(a[0], b[0]) and a[1] == b[1]
            assert np.array_equal(pol._affine.extrapolate(p), fit.extrapolate(p))
        assert pol._fallback.tri is pol.mapper.tri is not None and pol._affine.tri is pol.mapper.tri
        assert pol._fallback._transforms() is pol.mapper._transforms()
        n = (np.array([2 * k + 1, 4]) + 0.7) / 11  # a pair moves: a new revision, one new triangulation
        s.add(n, n)
