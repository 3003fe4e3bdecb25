"""transfer/mappers.py: the mappers behind the ``Mapper`` protocol (SC, barycentric, affine, identity).

That the SC, barycentric and affine mappers reproduce a per-axis affine learner, and that the SC regions are cached
and rebuilt, is tested in tests/unit/transfer/test_step.py; that the SC mapper never builds on a sliver in
tests/unit/transfer/scm/test_rectmap.py. Here the protocol's other promises: no region before three non-collinear
refined pairs, ``nearest_on_hull``, the barycentric mapper's exactness for any affine learner, the affine fit's
extrapolation, the identity baseline, the SC cache's bound, and ``make_mapper``'s refusal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.domain import Bounds
from transfer.mappers import (
    MAPPERS,
    AffineMapper,
    BarycentricMapper,
    IdentityMapper,
    ScmMapper,
    make_mapper,
)
from transfer.scm import is_simple_ccw
from transfer.scm._polygon import _smallest_angle, quad_pair_score
from transfer.store import PairStore

UNIT = Bounds((0.0, 1.0), (0.0, 1.0))  # normalised = physical: the pairs below read directly


def _store(pairs: list[tuple[list[float], list[float]]]) -> PairStore:
    s = PairStore(UNIT, UNIT, k_min=1)
    for t, l in pairs:
        s.add(np.array(t), np.array(l))
    return s


def _grid_store(f, n: int = 5) -> PairStore:
    """Refined pairs on an n x n grid of learner commands (one per cell), teacher parts f(learner part)."""
    g = 0.05 + 0.9 * np.linspace(0.0, 1.0, n)
    return _store([(list(f(np.array([a, b]))), [a, b]) for a in g for b in g])


def test_make_mapper_knows_its_four_mappers_and_refuses_others() -> None:
    s = _store([])
    for name, cls in MAPPERS.items():
        m = make_mapper(name, s)
        assert isinstance(m, cls) and m.name == name and m.store is s
    with pytest.raises(ValueError, match="unknown mapper 'sc'; known: scm, barycentric, affine, identity"):
        make_mapper("sc", s)


@pytest.mark.parametrize("cls", [ScmMapper, BarycentricMapper, AffineMapper])
def test_no_region_before_three_non_collinear_refined_pairs(cls) -> None:
    t = np.array([0.5, 0.5])
    assert cls(_store([])).map_normalised(t) is None and cls(_store([])).nearest_on_hull(t) is None
    two = _store([([0.1, 0.1], [0.1, 0.1]), ([0.9, 0.9], [0.9, 0.9])])
    assert cls(two).map_normalised(t) is None
    line = _store([([0.1, 0.1], [0.1, 0.1]), ([0.5, 0.5], [0.5, 0.5]), ([0.9, 0.9], [0.9, 0.9])])
    m = cls(line)
    assert m.map_normalised(t) is None and m.nearest_on_hull(t) is None and m.tri is None
    # pairs off the line: now there is a region (the mapper follows the store's revision)
    for p in ([0.9, 0.2], [0.2, 0.9]):
        line.add(np.array(p), np.array(p))
    assert cls(line).map_normalised(np.array([0.6, 0.4])) is not None
    assert m.map_normalised(np.array([0.6, 0.4])) is not None


def test_barycentric_is_exact_for_any_affine_learner_and_names_its_triangle() -> None:
    A = np.array([[0.6, 0.3], [-0.2, 0.7]])  # rotation and shear: not per axis
    b = np.array([0.1, 0.2])
    s = _grid_store(lambda l: np.linalg.solve(A, l - b))  # teacher part t with A t + b = l
    m = BarycentricMapper(s)
    ids = set(s.refined_arrays()[0].tolist())
    rng = np.random.default_rng(2)
    T = s.refined_arrays()[2]
    for _ in range(40):
        w = rng.dirichlet(np.ones(3))
        t = w @ T[rng.choice(len(T), 3, replace=False)]  # inside the hull of the pairs
        res = m.map_normalised(t)
        assert res is not None
        l, region = res
        np.testing.assert_allclose(l, A @ t + b, atol=1e-12)
        assert len(region) == 3 and set(region) <= ids
    # at a refined pair, exactly its learner part
    i = 7
    got = m.map_normalised(T[i])
    assert got is not None and np.allclose(got[0], s.refined_arrays()[3][i], atol=1e-12)


def test_outside_the_hull_there_is_no_region_and_nearest_on_hull_says_where_it_is() -> None:
    s = _grid_store(lambda l: l)  # pairs span [0.05, 0.95]^2
    for cls in (ScmMapper, BarycentricMapper, AffineMapper):
        m = cls(s)
        assert m.map_normalised(np.array([0.99, 0.5])) is None
        q, d = m.nearest_on_hull(np.array([0.99, 0.5]))
        assert d == pytest.approx(0.04) and q == pytest.approx([0.95, 0.5], abs=1e-8)
        assert m.map_normalised(q) is not None  # a hair inside: the point location finds its triangle
        q, d = m.nearest_on_hull(np.array([1.25, -0.35]))  # beyond a corner: the corner
        assert q == pytest.approx([0.95, 0.05], abs=1e-8) and d == pytest.approx(math.hypot(0.3, 0.4))


def test_the_affine_fit_maps_only_inside_the_region_but_extrapolates_anywhere() -> None:
    s = _grid_store(lambda l: 0.5 * l + 0.2)  # l = 2 (t - 0.2)
    m = AffineMapper(s)
    assert AffineMapper(_store([])).extrapolate(np.array([0.5, 0.5])) is None
    far = np.array([0.9, 0.1])  # outside the teacher parts' hull [0.225, 0.675]^2
    assert m.map_normalised(far) is None
    np.testing.assert_allclose(m.extrapolate(far), 2 * (far - 0.2), atol=1e-12)
    l, region = m.map_normalised(np.array([0.4, 0.5]))
    np.testing.assert_allclose(l, [0.4, 0.6], atol=1e-12)
    assert len(region) == 25  # every refined pair is in the fit


def test_identity_applies_the_teacher_command_clipped_into_the_learners_box() -> None:
    s = PairStore(Bounds((0.0, 1.0), (-0.5, 0.5)), Bounds((0.0, 2.0), (-1.0, 1.0)), k_min=1)
    m = IdentityMapper(s)
    l, region = m.map_normalised(np.array([0.25, 0.5]))  # teacher (0.5, 0.0): inside the learner's box
    assert region == () and l == pytest.approx([0.5, 0.5])
    l, _ = m.map_normalised(np.array([1.0, 1.0]))  # teacher (2, 1): clipped to the learner's (1, 0.5)
    assert l == pytest.approx([1.0, 1.0])
    t = np.array([0.3, 0.7])
    q, d = m.nearest_on_hull(t)
    assert d == 0.0 and q.tolist() == t.tolist() and q is not t


def test_the_sc_cache_is_bounded_and_least_recently_used() -> None:
    s = _grid_store(lambda l: l * np.array([1.0, 0.8]) + 0.05)
    T = s.refined_arrays()[2]
    a, b = T[[0, 1, 5]].mean(axis=0), T[[18, 19, 23]].mean(axis=0)  # two distant triangles' points
    m = ScmMapper(s)
    for t in (a, b, a, b):
        assert m.map_normalised(t) is not None
    assert m.builds == 2  # built once each, then served from the cache
    small = ScmMapper(s, cache_size=1)
    for t in (a, b, a):
        small.map_normalised(t)
    assert small.builds == 3 and len(small._quads) == 1  # a was evicted by b, built again


def test_smallest_angle_of_simple_shapes() -> None:
    sq = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert _smallest_angle(sq) == pytest.approx(math.pi / 2)
    kite = np.array([[0.0, 0.0], [2.0, -0.2], [4.0, 0.0], [2.0, 0.2]])
    assert _smallest_angle(kite) == pytest.approx(2 * math.atan2(0.2, 2.0))


def test_a_regions_shape_score_is_its_polygons_smallest_angle_or_refused_where_either_is_not_valid() -> None:
    """The compiled score the SC mapper ranks its candidate quadrilaterals by (``quad_pair_score``) is the smaller of
    the two polygons' smallest angles (numpy's arithmetic on the same edges) to the last few units in the last place,
    and -1 exactly where the polygon check refuses either (crossed, clockwise, repeated or flat vertices). Not bit for
    bit: numpy's vectorised ``arctan2`` (its AVX-512 loops, on a CPU that has them) and the compiled kernel's scalar
    one may round the same angle apart by an ulp."""
    def smallest(q: np.ndarray) -> float:
        nxt = np.concatenate((q[1:], q[:1])) - q
        prev = np.concatenate((nxt[-1:], nxt[:-1]))
        return float(np.min(np.pi - np.arctan2(prev[:, 0] * nxt[:, 1] - prev[:, 1] * nxt[:, 0],
                                               (prev * nxt).sum(axis=1))))

    rng = np.random.default_rng(7)
    valid = 0
    for i in range(3000):
        t, lrn = rng.random((4, 2)), rng.random((4, 2))
        if i % 5 == 0:
            lrn = t[::-1].copy()  # clockwise
        elif i % 5 == 1:
            lrn = t.copy()
            lrn[2] = lrn[1]  # a repeated vertex
        ok = is_simple_ccw(t) and is_simple_ccw(lrn)
        valid += ok
        score = quad_pair_score(t, lrn)
        if ok:
            assert score == pytest.approx(min(smallest(t), smallest(lrn)), rel=1e-13, abs=1e-15)
        else:
            assert score == -1.0
    assert valid > 50  # valid ones were checked too (two in five are refused by construction)


@pytest.mark.parametrize("cls", [ScmMapper, BarycentricMapper, AffineMapper, IdentityMapper])
def test_map_many_gives_each_rows_own_map_inside_outside_and_on_the_pairs(cls) -> None:
    """``map_many``: a hole search maps a row of commands at once; each row's result is the one ``map_normalised``
    gives it alone (the SC mapper's bit for bit: it groups the rows of one quadrilateral into one call of a map
    that maps each point on its own), None where it has no region."""
    s = _grid_store(lambda l: np.array([l[0] ** 1.5, 0.8 * l[1] + 0.1 * l[0]]))
    rng = np.random.default_rng(5)
    P = np.vstack([rng.uniform(-0.1, 1.1, (60, 2)), s.refined_arrays()[2][:5], [[0.5, 0.5], [0.5, 0.5]]])
    alone, many = cls(s), cls(s)
    got = many.map_many(P)
    assert len(got) == len(P) and cls(s).map_many(np.zeros((0, 2))) == []
    for p, g in zip(P, got):
        want = alone.map_normalised(p)
        assert (g is None) == (want is None), p
        if want is not None:
            assert g[1] == want[1]
            if cls is BarycentricMapper:  # the weights of every row at once: the same to rounding
                np.testing.assert_allclose(g[0], want[0], rtol=0, atol=1e-14)
            else:
                assert g[0].tolist() == want[0].tolist()
    if cls is ScmMapper:
        assert many.builds == alone.builds  # each quadrilateral built once either way
    assert any(g is None for g in got) or cls is IdentityMapper
    assert any(g is not None for g in got)
