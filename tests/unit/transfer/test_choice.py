"""transfer/choice.py: the transfer's choice, per command, between the SC map and linear interpolation.

What the grid experiment measures of it is docs/PAPER.md's; here its promises: every command it serves is exactly the
SC mapper's or the barycentric mapper's answer for it, named by that map's method; where the two agree within
``AGREE`` it is the linear one (exact for an affine learner); a command whose SC maps disagree with the line by more
than their own spread (a triangle across a hole of a curved response) is the SC map's; and the policy without the
choice is the paper's SC map wherever it has a region."""

from __future__ import annotations

import numpy as np

from transfer.choice import AGREE, TRUST, MapChoice
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


def _holey(rng) -> list:
    """Pairs dense in one corner and sparse elsewhere: triangles of every size, some across holes."""
    dense = 0.05 + 0.4 * rng.random((25, 2))
    sparse = np.array([[0.95, 0.05], [0.05, 0.95], [0.95, 0.95], [0.7, 0.5], [0.5, 0.75]])
    return [*dense, *sparse]


def test_every_answer_is_one_of_the_two_maps_and_named_by_it() -> None:
    rng = np.random.default_rng(1)
    store = _store(_cubic, _holey(rng))
    choice = MapChoice(ScmMapper(store))
    scm, lin = ScmMapper(store), BarycentricMapper(store)
    seen = set()
    for t in 0.1 + 0.8 * rng.random((300, 2)):
        got = choice.map_normalised(t)
        s = scm.map_normalised(t)
        if s is None:
            assert got is None
            continue
        b = lin.map_normalised(t)
        assert got is not None
        l, method, region = got
        seen.add(method)
        ref = s if method == "scm" else b
        assert method in ("scm", "barycentric") and np.array_equal(l, ref[0]) and region == ref[1]
    assert seen == {"scm", "barycentric"}  # on these pairs neither map is right everywhere


def test_the_rule_as_documented() -> None:
    # recomputed from the mappers' own answers: linear where the maps agree within AGREE; else the SC map when the
    # spread of its quadrilaterals' maps is below TRUST times its distance to the line (one quadrilateral: one cell)
    rng = np.random.default_rng(2)
    store = _store(_cubic, _holey(rng))
    scm, lin = ScmMapper(store), BarycentricMapper(store)
    choice = MapChoice(scm)
    counted = {"agree": 0, "scm": 0, "barycentric": 0}
    for t in 0.1 + 0.8 * rng.random((300, 2)):
        got = choice.map_normalised(t)
        if got is None:
            continue
        s, b = scm.map_normalised(t), lin.map_normalised(t)
        d = float(np.max(np.abs(s[0] - b[0])))
        outs = choice._all_quads(t, scm._simplex(t))
        if d <= AGREE:
            want, key = "barycentric", "agree"
        elif len(outs) < 2:
            want = "scm" if d > 1.0 / min(store.grid) else "barycentric"
            key = want
        else:
            want = "scm" if float(np.max(np.ptp(np.array(outs), axis=0))) < TRUST * d else "barycentric"
            key = want
        assert got[1] == want
        counted[key] += 1
    assert all(n > 0 for n in counted.values()), counted


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
