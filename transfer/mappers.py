"""Mappers from a teacher command to a learner command built on the refined pairs of a :class:`PairStore`.

All mappers work in normalised coordinates (teacher side by the teacher's bounds, learner side by the learner's)
and share one interface, so the SC map can be compared honestly with simpler alternatives:

- :class:`ScmMapper`: the paper's method. Delaunay triangulation of the refined pairs' teacher parts; the triangle
  holding u_T joined with one neighbour gives the teacher quadrilateral, the same pairs the learner
  quadrilateral; both must be simple and counter-clockwise with no interior angle under ``MIN_QUAD_ANGLE`` (a
  sliver whose corners are almost collinear, as pairs learned along a limit of the command box make, has no
  accurate SC map and is not tried); among the valid neighbours the one whose two quadrilaterals have the largest
  smallest interior angle wins (the best-conditioned SC problem). The
  ``QuadTransfer`` of a triangle is cached and rebuilt when one of its pairs changes version.
- :class:`BarycentricMapper`: piecewise-linear interpolation on the same triangles.
- :class:`AffineMapper`: one least-squares affine map fitted on all refined pairs (used on the same region).
- :class:`IdentityMapper`: the paper's baseline, the teacher command applied as it is.

Every mapper implements the :class:`Mapper` protocol: ``map_normalised(t)`` returns ``(l, region)`` with ``l`` the
normalised learner command, or ``None`` when the mapper has no region for ``t`` (the policy then falls back);
``nearest_on_hull(t)`` the point of its region nearest to ``t`` and the distance (``None`` before it has one).
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import Delaunay, QhullError

from transfer.domain import clamp
from transfer.scm import QuadTransfer
from transfer.scm._polygon import quad_pair_score
from transfer.store import PairStore

Region = tuple[int, ...]
#: the smallest interior angle of a quadrilateral the SC mapper builds a map on, radians (1 degree)
MIN_QUAD_ANGLE = float(np.radians(1.0))
#: how far outside a triangle (barycentric units) a point still counts as in it: scipy's ``find_simplex`` tolerance
SIMPLEX_EPS = 100 * np.finfo(float).eps


class Mapper(Protocol):
    """Normalised teacher command -> normalised learner command over a store's refined pairs."""

    name: str
    store: PairStore

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], Region] | None:
        """``(l, region)`` for ``t``, or None where the mapper has no region."""
        ...

    def nearest_on_hull(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], float] | None:
        """The point of the mapper's region nearest to ``t`` and its distance; None before there is a region."""
        ...

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], Region] | None]:
        """``map_normalised`` of every row of ``P`` ``(n, 2)``: the same results, computed together where the
        mapper can (a hole search maps a row of slowed commands: :meth:`transfer.policy.GuidedPolicy._fill_target`)."""
        ...


class _Triangulated:
    """Shared Delaunay triangulation of the refined pairs' normalised teacher parts, rebuilt on store revision."""

    name = "base"

    def __init__(self, store: PairStore) -> None:
        self.store = store
        self._rev = -1
        self.tri: Delaunay | None = None
        self.ids = np.zeros(0, dtype=np.int64)
        self.vers = np.zeros(0, dtype=np.int64)
        self.T = np.zeros((0, 2))
        self.L = np.zeros((0, 2))
        self._edges: tuple[NDArray[np.float64], ...] | None = None  # nearest_on_hull's edges of this triangulation
        #: every triangle's barycentric transform (scipy's ``Delaunay.transform`` layout: ``(n, 3, 2)``, the inverse
        #: of the edge matrix and the third vertex), computed once per triangulation (see :meth:`_transforms`)
        self._bary: NDArray[np.float64] | None = None
        #: another mapper of the same store whose triangulation this one reads instead of building its own (the
        #: same Delaunay triangulation of the same points: a policy's SC mapper and its barycentric fallback)
        self.twin: _Triangulated | None = None

    def _sync(self) -> None:
        if self._rev == self.store.revision:
            return
        twin = self.twin
        if twin is not None:  # the twin's triangulation of the same refined pairs, built once for both
            twin._sync()
            self._rev = twin._rev
            self.ids, self.vers, self.T, self.L, self.tri = twin.ids, twin.vers, twin.T, twin.L, twin.tri
            self._edges = None
            self._bary = None
            self._rebuilt()
            return
        self._rev = self.store.revision
        self.ids, self.vers, self.T, self.L = self.store.refined_arrays()
        self.tri = None
        self._edges = None
        self._bary = None
        if self.ids.size >= 3:
            try:
                self.tri = Delaunay(self.T)
            except QhullError:  # all collinear: no triangle yet
                self.tri = None
        self._rebuilt()

    def _rebuilt(self) -> None:
        """Hook: the triangulation changed."""

    def _transforms(self) -> NDArray[np.float64]:
        """The barycentric transforms of every triangle, vectorised. scipy computes the same array lazily on the
        first ``find_simplex`` after each triangulation, one LAPACK call per triangle: 0.5-3 ms on 121 pairs, paid
        on every command after the store's refined pairs moved (the station's steady state); this is ~20 us."""
        if self._bary is None and self.twin is not None and self.twin.tri is self.tri:
            self._bary = self.twin._transforms()  # the twin's triangles: the same transforms
        if self._bary is None:
            assert self.tri is not None
            S = self.tri.simplices
            P = self.T
            r = P[S[:, 2]]
            a, b = P[S[:, 0]] - r, P[S[:, 1]] - r  # the edge matrix's columns
            det = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
            ok = np.abs(det) > 1e-300
            inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), np.nan)  # a degenerate triangle holds no point
            tr = np.empty((S.shape[0], 3, 2))
            tr[:, 0, 0], tr[:, 0, 1] = b[:, 1] * inv_det, -b[:, 0] * inv_det
            tr[:, 1, 0], tr[:, 1, 1] = -a[:, 1] * inv_det, a[:, 0] * inv_det
            tr[:, 2] = r
            self._bary = tr
        return self._bary

    def _simplex(self, t: NDArray[np.float64]) -> int:
        """The triangle holding ``t`` (the one it lies deepest in, on a shared edge), or -1: as scipy's
        ``find_simplex`` with its tolerance, over every triangle at once."""
        if self.tri is None:
            return -1
        tr = self._transforms()
        d0, d1 = t[0] - tr[:, 2, 0], t[1] - tr[:, 2, 1]
        l0 = tr[:, 0, 0] * d0 + tr[:, 0, 1] * d1
        l1 = tr[:, 1, 0] * d0 + tr[:, 1, 1] * d1
        depth = np.fmin(np.fmin(l0, l1), 1.0 - l0 - l1)  # fmin: a degenerate triangle's NaN never wins
        i = int(np.argmax(np.where(np.isnan(depth), -np.inf, depth)))  # = nan_to_num(nan=-inf) for argmax
        return i if depth[i] >= -SIMPLEX_EPS else -1

    def _simplices(self, P: NDArray[np.float64]) -> NDArray[np.int64]:
        """:meth:`_simplex` of every row of ``P`` ``(n, 2)`` in one pass over the triangles (the same arithmetic,
        element by element, so the same triangles)."""
        if self.tri is None:
            return np.full(len(P), -1, dtype=np.int64)
        tr = self._transforms()
        d0, d1 = P[:, :1] - tr[:, 2, 0], P[:, 1:] - tr[:, 2, 1]
        l0 = tr[:, 0, 0] * d0 + tr[:, 0, 1] * d1
        l1 = tr[:, 1, 0] * d0 + tr[:, 1, 1] * d1
        depth = np.fmin(np.fmin(l0, l1), 1.0 - l0 - l1)
        i = np.argmax(np.where(np.isnan(depth), -np.inf, depth), axis=1)
        return np.where(depth[np.arange(len(P)), i] >= -SIMPLEX_EPS, i, -1)

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], Region] | None:
        raise NotImplementedError

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], Region] | None]:
        """``map_normalised`` of every row of ``P`` (:class:`Mapper`); one by one here."""
        return [self.map_normalised(p) for p in P]

    def nearest_on_hull(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], float] | None:
        """The point of the triangulated region nearest to t (just inside its hull), and its distance."""
        self._sync()
        if self.tri is None:
            return None
        if self._edges is None and self.twin is not None and self.twin.tri is self.tri and self.twin._edges is not None:
            self._edges = self.twin._edges  # the twin's hull of the same triangulation
        if self._edges is None:  # the hull's edges, once per triangulation (a hot path: every "direct" command)
            P = self.T
            e = self.tri.convex_hull
            a = P[e[:, 0]]
            d = P[e[:, 1]] - a
            self._edges = (a, d, np.maximum((d * d).sum(axis=1), 1e-300), P.mean(axis=0))
        a, d, dd, centre = self._edges
        tt = clamp(((t - a) * d).sum(axis=1) / dd, 0.0, 1.0)
        q = a + tt[:, None] * d
        dist = np.hypot(*(q - t).T)
        i = int(np.argmin(dist))
        inside = q[i] + 1e-9 * (centre - q[i])  # a hair inside, so the point location finds its triangle
        return inside, float(dist[i])


class ScmMapper(_Triangulated):
    """The paper's SC transfer on quadrilateral mapping regions (see the module docstring)."""

    name = "scm"

    def __init__(self, store: PairStore, cache_size: int = 512) -> None:
        super().__init__(store)
        self.cache_size = int(cache_size)
        # pair ids of a quadrilateral (in ccw order) + their versions -> QuadTransfer (None: not usable)
        self._quads: OrderedDict[tuple, QuadTransfer | None] = OrderedDict()
        self._by_simplex: dict[int, list[tuple[Region, tuple]]] = {}
        self.builds = 0  # QuadTransfers constructed (for benchmarks and tests)

    def _rebuilt(self) -> None:
        self._by_simplex = {}

    def _candidates(self, s: int) -> list[tuple[Region, tuple]]:
        """Valid quadrilaterals around simplex s, best first: (local vertex indices, cache key)."""
        tri = self.tri
        assert tri is not None
        a, b, c = (int(v) for v in tri.simplices[s])
        P = self.T
        if (P[b, 0] - P[a, 0]) * (P[c, 1] - P[a, 1]) - (P[b, 1] - P[a, 1]) * (P[c, 0] - P[a, 0]) < 0:
            b, c = c, b  # make (a, b, c) counter-clockwise
        verts = (a, b, c)
        scored = []
        for k, nb in enumerate(tri.neighbors[s]):
            if nb < 0:
                continue
            opp = int(tri.simplices[s][k])  # the vertex of s opposite the neighbour
            i = verts.index(opp)
            x, y, z = verts[i], verts[(i + 1) % 3], verts[(i + 2) % 3]  # shared edge is (y, z)
            d = next(int(v) for v in tri.simplices[nb] if int(v) not in (y, z))
            quad = (x, y, d, z)
            idx = list(quad)
            score = quad_pair_score(self.T[idx], self.L[idx])  # -1 where either polygon is not valid
            if score < MIN_QUAD_ANGLE:
                continue
            key = tuple((int(self.ids[v]), int(self.vers[v])) for v in quad)
            scored.append((score, quad, key))
        scored.sort(key=lambda e: -e[0])
        return [(q, key) for _, q, key in scored]

    def _candidates_of(self, s: int) -> list[tuple[Region, tuple]]:
        """:meth:`_candidates` of simplex s, computed once per triangulation."""
        cands = self._by_simplex.get(s)
        if cands is None:
            cands = self._by_simplex[s] = self._candidates(s)
        return cands

    def _transfer(self, quad: Region, key: tuple) -> QuadTransfer | None:
        if key in self._quads:
            self._quads.move_to_end(key)
            return self._quads[key]
        try:
            qt: QuadTransfer | None = QuadTransfer(self.T[list(quad)], self.L[list(quad)])
            self.builds += 1
        except ValueError:
            qt = None
        self._quads[key] = qt
        if len(self._quads) > self.cache_size:
            self._quads.popitem(last=False)
        return qt

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], Region] | None:
        self._sync()
        s = self._simplex(t)
        if s < 0:
            return None
        for quad, key in self._candidates_of(s):
            qt = self._transfer(quad, key)
            if qt is None:
                continue
            out = qt(t.reshape(1, 2), outside="nan")[0]
            if np.all(np.isfinite(out)):
                return out, tuple(int(self.ids[v]) for v in quad)
        return None

    def prepare(self, t: NDArray[np.float64]) -> bool:
        """Build the SC map :meth:`map_normalised` would try first for ``t`` if it is not cached yet, without mapping:
        True when one was built. A caller that cuts its work into short steps builds in one and maps in the next
        (:mod:`transfer.holes`); the map is the same either way."""
        self._sync()
        s = self._simplex(t)
        for quad, key in self._candidates_of(s) if s >= 0 else ():
            if key in self._quads:
                return False
            self._transfer(quad, key)
            return True
        return False

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], Region] | None]:
        """``map_normalised`` of every row of ``P`` (:class:`Mapper`): the triangles located in one pass, and the
        rows that try the same quadrilateral mapped by one call of its SC map (it maps each point on its own, so
        the results are those of one call per row)."""
        self._sync()
        res: list[tuple[NDArray[np.float64], Region] | None] = [None] * len(P)
        if self.tri is None or not len(P):
            return res
        simplex = self._simplices(P)
        cands: dict[int, list[tuple[Region, tuple]]] = {}
        trying: dict[int, int] = {}  # row -> index of the candidate quadrilateral it tries next
        for i, s in enumerate(simplex.tolist()):
            if s >= 0:
                if s not in cands:
                    cands[s] = self._candidates_of(s)
                if cands[s]:
                    trying[i] = 0
        while trying:
            groups: dict[tuple, tuple[Region, list[int]]] = {}
            for i, k in trying.items():
                quad, key = cands[int(simplex[i])][k]
                groups.setdefault(key, (quad, []))[1].append(i)
            later: dict[int, int] = {}
            for key, (quad, rows) in groups.items():
                qt = self._transfer(quad, key)
                out = qt(P[rows], outside="nan") if qt is not None else None
                for j, i in enumerate(rows):
                    if out is not None and np.all(np.isfinite(out[j])):
                        res[i] = out[j], tuple(int(self.ids[v]) for v in quad)
                    elif trying[i] + 1 < len(cands[int(simplex[i])]):
                        later[i] = trying[i] + 1
            trying = later
        return res


class BarycentricMapper(_Triangulated):
    """Piecewise-linear interpolation on the Delaunay triangles of the refined pairs."""

    name = "barycentric"

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], Region] | None:
        self._sync()
        s = self._simplex(t)
        if s < 0:
            return None
        assert self.tri is not None
        T = self._transforms()[s]
        lam = T[:2].dot(t - T[2])
        bary = np.array([lam[0], lam[1], 1.0 - lam.sum()])
        verts = self.tri.simplices[s]
        return bary @ self.L[verts], tuple(int(self.ids[v]) for v in verts)

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], Region] | None]:
        """``map_normalised`` of every row of ``P`` (:class:`Mapper`), every row's triangle and weights at once."""
        self._sync()
        if self.tri is None or not len(P):
            return [None] * len(P)
        simplex = self._simplices(P)
        tr = self._transforms()[simplex]
        lam = np.einsum("nij,nj->ni", tr[:, :2], P - tr[:, 2])
        bary = np.column_stack([lam, 1.0 - lam.sum(axis=1)])
        verts = self.tri.simplices[simplex]
        out = np.einsum("nk,nkj->nj", bary, self.L[verts])
        ids = self.ids[verts]
        return [(out[i], tuple(ids[i].tolist())) if simplex[i] >= 0 else None for i in range(len(P))]


class AffineMapper(_Triangulated):
    """A single least-squares affine map l = A t + b fitted on all refined pairs, used where the others are."""

    name = "affine"

    def _rebuilt(self) -> None:
        self._coef = None
        if self.ids.size >= 3:
            X = np.hstack([self.T, np.ones((self.T.shape[0], 1))])
            coef, _, rank, _ = np.linalg.lstsq(X, self.L, rcond=None)
            if rank == 3:
                self._coef = coef

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], Region] | None:
        self._sync()
        if self._coef is None or self._simplex(t) < 0:
            return None
        return np.append(t, 1.0) @ self._coef, tuple(int(i) for i in self.ids)

    def extrapolate(self, t: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """The affine fit at t wherever t is (None before there is a fit): a guess, not a mapping."""
        self._sync()
        return None if self._coef is None else np.append(t, 1.0) @ self._coef


class IdentityMapper:
    """The paper's baseline: the teacher command is applied to the learner as it is (clipped into the learner's
    box). It needs no pairs: its region is the whole teacher domain."""

    name = "identity"

    def __init__(self, store: PairStore) -> None:
        self.store = store

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], Region]:
        lb = self.store.learner_bounds
        u = lb.clip(self.store.teacher_bounds.denormalise(np.asarray(t, dtype=float)))
        return lb.normalise(u), ()

    def nearest_on_hull(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        return np.asarray(t, dtype=float).copy(), 0.0

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], Region] | None]:
        """``map_normalised`` of every row of ``P`` (:class:`Mapper`)."""
        return [self.map_normalised(p) for p in P]


MAPPERS = {"scm": ScmMapper, "barycentric": BarycentricMapper, "affine": AffineMapper, "identity": IdentityMapper}


def make_mapper(name: str, store: PairStore) -> Mapper:
    """A mapper by name: ``scm``, ``barycentric``, ``affine`` or ``identity``."""
    try:
        return MAPPERS[name](store)
    except KeyError:
        raise ValueError(f"unknown mapper {name!r}; known: {', '.join(MAPPERS)}") from None
