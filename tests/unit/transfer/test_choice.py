"""transfer/choice.py: the transfer's choice, per command, between the SC map and linear interpolation.

What the grid experiment measures of it is docs/PAPER.md's; here its promises: every command it serves is exactly the
SC mapper's or the barycentric mapper's answer for it, named by that map's method; a command in a triangle that spans
a hole (a teacher side longer than ``HOLE``), whose learner side is at least ``GAIN`` times its teacher side and whose
line misses its neighbours' far pairs by more than ``BEND`` is the SC map's, in any other the line's (exact for an
affine learner, holes or not); and the policy without the choice is the paper's SC map wherever it has a region."""

from __future__ import annotations

import numpy as np

from transfer.choice import BEND, GAIN, HOLE, MapChoice
from transfer.domain import Bounds
from transfer.mappers import BarycentricMapper, ScmMapper
from transfer.policy import make_policy
from transfer.store import PairStore

UNIT = Bounds((0.0, 1.0), (0.0, 1.0))


def _store(f, pts) -> PairStore:
    s = PairStore(UNIT, UNIT, k_min=1)
    for l in pts:
        s.add(f(np.asarray(l, dtype=float)), np.asarray(l, dtype=float))
    return s


def _cubic(l):
    """A per-axis convex response (the paper's h_v = v^3 kind), in normalised units."""
    return np.array([0.1 + 0.8 * l[0] ** 3, 0.1 + 0.8 * l[1] ** 3])


def _wavy(l):
    """The cubic response with a ripple across the axes: curvature a small triangle's line misses."""
    return _cubic(l) + 0.08 * np.sin(9.0 * l[::-1])


def _gridded(rng) -> list:
    """A noisy 9 x 9 grid of pairs with a hole in the middle: small triangles and a few spanning the hole."""
    g = np.linspace(0.05, 0.95, 9)
    pts = np.array([[a, b] for a in g for b in g if not (0.4 < a < 0.75 and 0.4 < b < 0.75)])
    return list(pts + 0.02 * rng.standard_normal(pts.shape))


def _big_hole(rng) -> list:
    """A noisy 9 x 9 grid of pairs with a wide hole in the middle: the triangles across it are big on both sides."""
    g = np.linspace(0.05, 0.95, 9)
    pts = np.array([[a, b] for a in g for b in g if not (0.2 < a < 0.8 and 0.2 < b < 0.8)])
    return list(pts + 0.02 * rng.standard_normal(pts.shape))


def _holey(rng) -> list:
    """Pairs dense in one corner and sparse elsewhere: triangles of every size, some across holes."""
    dense = 0.05 + 0.4 * rng.random((25, 2))
    sparse = np.array([[0.95, 0.05], [0.05, 0.95], [0.95, 0.95], [0.7, 0.5], [0.5, 0.75]])
    return [*dense, *sparse]


def test_every_answer_is_one_of_the_two_maps_and_named_by_it() -> None:
    rng = np.random.default_rng(1)
    store = _store(_wavy, _gridded(rng))
    choice = MapChoice(ScmMapper(store))
    scm, lin = ScmMapper(store), BarycentricMapper(store)
    seen = set()
    for t in 0.1 + 0.8 * rng.random((600, 2)):
        got = choice.map_normalised(t)
        s, b = scm.map_normalised(t), lin.map_normalised(t)
        if got is None:  # no triangle, or a hole without an SC region: the policy's fallback
            assert b is None or s is None
            continue
        l, method, region = got
        seen.add(method)
        ref = s if method == "scm" else b
        assert method in ("scm", "barycentric") and ref is not None
        assert np.array_equal(l, ref[0]) and region == ref[1]
    assert seen == {"scm", "barycentric"}  # on these pairs neither map is right everywhere


def _by_hand(scm: ScmMapper, k: int) -> tuple[float, float, float]:
    """Triangle ``k``'s longest teacher side, longest learner side and its line's mean miss at its neighbours' far
    pairs, computed one by one from the pairs (the line as the affine map through the triangle's three pairs)."""
    verts = [int(v) for v in scm.tri.simplices[k]]
    P, Q = scm.T[verts], scm.L[verts]
    A = np.linalg.solve(np.column_stack([P, np.ones(3)]), Q)  # l = [t, 1] @ A through the three pairs
    misses = []
    for nb in scm.tri.neighbors[k]:
        if nb >= 0:
            (far,) = set(int(v) for v in scm.tri.simplices[nb]) - set(verts)
            misses.append(float(np.hypot(*(np.append(scm.T[far], 1.0) @ A - scm.L[far]))))
    def side(X):
        return max(float(np.hypot(*(X[i] - X[i - 1]))) for i in range(3))
    return side(P), side(Q), float(np.mean(misses)) if misses else 0.0


def test_the_rule_as_documented() -> None:
    # recomputed from the pairs: the SC mapper's answer in a triangle with a teacher side longer than HOLE, a learner
    # side at least GAIN times it, and a line that misses its neighbours' far pairs by more than BEND; the
    # triangle's line in every other
    rng = np.random.default_rng(0)
    store = _store(_wavy, _gridded(rng))
    scm, lin = ScmMapper(store), BarycentricMapper(store)
    choice = MapChoice(scm)
    counted = {"scm": 0, "barycentric": 0}
    for t in 0.1 + 0.8 * rng.random((1500, 2)):
        got = choice.map_normalised(t)
        k = scm._simplex(t)
        if k < 0:
            assert got is None
            continue
        t_side, l_side, miss = _by_hand(scm, k)
        want = "scm" if t_side > HOLE and l_side >= GAIN * t_side and miss > BEND else "barycentric"
        ref = (scm if want == "scm" else lin).map_normalised(t)
        if ref is None:  # a hole the SC mapper has no region for: the policy's fallback, not the choice
            assert want == "scm" and got is None
            continue
        assert got is not None and got[1] == want and np.array_equal(got[0], ref[0]) and got[2] == ref[1]
        counted[want] += 1
    assert counted["scm"] > 10 and counted["barycentric"] > 500, counted


def test_the_line_check_is_each_triangles_own() -> None:
    store = _store(_wavy, _gridded(np.random.default_rng(2)))
    choice = MapChoice(ScmMapper(store))
    choice.scm._sync()
    check = choice.line_check()
    for k in range(len(choice.scm.tri.simplices)):
        assert abs(check[k] - _by_hand(choice.scm, k)[2]) < 1e-9


def test_a_big_triangle_whose_line_passes_its_check_is_the_lines() -> None:
    # an affine learner with a hole in its pairs: triangles across the hole, whose line misses nothing: the line,
    # exact, everywhere (the triangle's size alone would give the hole to the SC map and its distortion)
    A = np.array([[0.6, 0.05], [-0.03, 0.62]])

    def f(l):
        return A @ l + np.array([0.1, 0.1])

    store = _store(f, _big_hole(np.random.default_rng(3)))
    choice = MapChoice(ScmMapper(store))
    big = 0
    for l_true in 0.1 + 0.8 * np.random.default_rng(3).random((400, 2)):
        t = f(l_true)
        k = choice.scm._simplex(t)
        got = choice.map_normalised(t)
        if k < 0:
            continue
        t_side, l_side, _ = _by_hand(choice.scm, k)
        big += t_side > HOLE and l_side >= GAIN * t_side  # spans a hole where the response is flat
        assert got is not None and got[1] == "barycentric" and np.allclose(got[0], l_true, atol=1e-9)
    assert big > 20


def test_a_big_triangle_whose_sides_are_alike_is_the_lines() -> None:
    # the ripple bends the response across the hole (the lines fail their check) but the learner's sides are the
    # teacher's size there: the line, not the SC map of the long thin quadrilaterals around the hole
    def f(l):
        return 0.1 + 0.8 * l + 0.1 * np.sin(5.0 * l[::-1])

    store = _store(f, _big_hole(np.random.default_rng(3)))
    scm = ScmMapper(store)
    choice = MapChoice(scm)
    scm._sync()
    bent = 0
    for k in range(len(scm.tri.simplices)):
        t_side, l_side, miss = _by_hand(scm, k)
        centroid = scm.T[scm.tri.simplices[k]].mean(axis=0)
        if t_side > HOLE and miss > BEND and scm.map_normalised(centroid) is not None:
            bent += 1
            assert l_side < GAIN * t_side
            got = choice.map_normalised(centroid)
            assert got is not None and got[1] == "barycentric"
    assert bent >= 2


def test_many_commands_at_once_are_each_commands_own_answer() -> None:
    rng = np.random.default_rng(5)
    store = _store(_wavy, _gridded(rng))
    choice = MapChoice(ScmMapper(store))
    P = rng.random((400, 2))
    many = choice.map_many(P)
    one = [MapChoice(ScmMapper(store)).map_normalised(p) for p in P]
    assert {g[1] for g in many if g is not None} == {"scm", "barycentric"}
    for a, b in zip(many, one):
        assert (a is None) == (b is None)
        if a is not None:
            assert a[1] == b[1] and a[2] == b[2] and np.allclose(a[0], b[0], rtol=0, atol=1e-12)


def test_an_affine_learner_is_served_exactly_where_the_maps_agree() -> None:
    A = np.array([[0.6, 0.1], [-0.05, 0.7]])

    def f(l):
        return A @ l + np.array([0.1, 0.15])

    g = 0.05 + 0.9 * np.linspace(0.0, 1.0, 6)
    store = _store(f, [[a, b] for a in g for b in g])
    choice = MapChoice(ScmMapper(store))
    lin = 0
    for l_true in 0.1 + 0.8 * np.random.default_rng(3).random((200, 2)):
        got = choice.map_normalised(f(l_true))
        if got is not None and got[1] == "barycentric":
            lin += 1
            assert np.allclose(got[0], l_true, atol=1e-9)
    assert lin > 100


def test_the_policy_without_the_choice_is_the_papers_sc_map() -> None:
    rng = np.random.default_rng(4)
    store = _store(_cubic, _holey(rng))
    with_, without = (make_policy(store, "scm", seed=0, fill_budget=0.0, choice=c) for c in (True, False))
    lin = BarycentricMapper(store)
    n_scm = {True: 0, False: 0}
    for t in 0.1 + 0.8 * rng.random((300, 2)):
        a, b = with_.map(t, explore=False), without.map(t, explore=False)
        n_scm[True] += a.method == "scm"
        n_scm[False] += b.method == "scm"
        if a.method == "scm":  # chosen: the paper's SC map itself
            assert b.method == "scm" and np.array_equal(a.u_L, b.u_L)
        elif b.method == "scm":  # not chosen: the line of the triangle, where the paper maps by SC
            assert a.method == "barycentric" and np.allclose(a.u_L, lin.map_normalised(t)[0], atol=1e-12)
    assert n_scm[False] > n_scm[True] >= 0 and n_scm[False] > 50
