"""Which map serves a command inside the learned region: the SC map, or linear interpolation (docs/PAPER.md, "The
transfer's choice of map").

On the refined pairs a mission leaves (docs/PAPER.md, ``sim grid``) neither map is better everywhere: linear
interpolation on the triangle of pairs holding the command (:class:`transfer.mappers.BarycentricMapper`'s) is exact
where the learner's response is nearly affine across the triangle, and the SC map's conformal distortion is its error
there (the map through two rectangles of different moduli is not affine even where the pairs are); the SC map
(:class:`transfer.mappers.ScmMapper`, paper Section 4) is the better guess where the response bends across a big
triangle, whose quadrilateral bends the map by a fourth pair. :class:`MapChoice` decides per triangle from the pairs
alone, with no knowledge of the learner and no second map. The SC map (``scm``) serves a command when the triangle of
the SC mapper's own Delaunay triangulation holding it (teacher domain, normalised) passes all three tests:

- *it spans a hole*: its longest teacher side exceeds :data:`HOLE` (in a small one the pairs are dense and the line
  is as good as the response is smooth);
- *the response is flat across it*: its longest learner side is at least :data:`GAIN` times its longest teacher side
  (a wide range of learner commands answers with a narrow range of teacher-equivalent ones: where the learner's
  response saturates, which a line misses; where the two sides are alike the response is near affine and the SC map
  of the long, thin quadrilaterals there only adds its distortion);
- *the line fails its own check*: the triangle's line, carried to the far pair of each neighbouring triangle (the
  fourth pair of each quadrilateral the SC mapper can build around it, a pair the line did not use), misses it by
  more than :data:`BEND` on average (normalised learner units): the response bends across the triangle.

Every other command in the triangulation gets the triangle's line (``barycentric``). Where the SC mapper has no
region in a triangle the rule gives to it, there is no answer (the policy then falls back as without the choice: the
same line).

Pure: no I/O, no clock. The three tests are computed for all triangles at once, once per triangulation, with the
barycentric transforms the mapper keeps; a command in a line triangle costs one dot product, one in an SC triangle the
SC map alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from transfer.mappers import Region, ScmMapper

#: a triangle whose longest teacher side exceeds this (normalised teacher units: about three cells of the default
#: 11 x 11 store) spans a hole of the map; the line serves every smaller one
HOLE = 0.28
#: the SC map only where a triangle's longest learner side is at least this many times its longest teacher side
#: (both normalised): the learner's response is flat across it
GAIN = 1.5
#: the SC map only where the triangle's line misses the far pairs of its neighbouring triangles by more than this on
#: average (normalised learner units): the response bends across it
BEND = 0.1


class MapChoice:
    """The SC map or linear interpolation, per command (module docstring). ``map_normalised`` returns ``(l, method,
    region)`` with ``method`` ``"scm"`` or ``"barycentric"``, or None outside the triangulation or where the SC mapper
    has no region in a triangle that spans a hole (the policy falls back as without the choice)."""

    def __init__(self, scm: ScmMapper) -> None:
        self.scm = scm
        self.store = scm.store
        self._holes_of: object = None  # the triangulation ``_holes`` was computed on
        self._holes: NDArray[np.bool_] = np.zeros(0, dtype=bool)

    def holes(self) -> NDArray[np.bool_]:
        """Per triangle of the SC mapper's current triangulation: whether the SC map serves it, all three tests of
        the module docstring (computed for all at once, once per triangulation)."""
        m = self.scm
        if self._holes_of is not m.tri:
            if m.tri is None:
                self._holes = np.zeros(0, dtype=bool)
            else:
                S = m.tri.simplices
                t_side = _longest_side(m.T[S])
                holes = t_side > HOLE
                big = np.flatnonzero(holes)  # the other two tests only where the size leaves them to decide
                if big.size:
                    flat = _longest_side(m.L[S[big]]) >= GAIN * t_side[big]
                    holes[big[~flat]] = False
                    big = big[flat]
                    holes[big] = self.line_check(big) > BEND
                self._holes = holes
            self._holes_of = m.tri
        return self._holes

    def line_check(self, ks: NDArray[np.intp] | None = None) -> NDArray[np.float64]:
        """Per triangle (of ``ks``, default all): the mean distance (normalised learner units) by which its line,
        carried to the far pair of each neighbouring triangle, misses that pair's learner command (0 for a triangle
        without neighbours, NaN for a degenerate one)."""
        m = self.scm
        assert m.tri is not None
        S, N = m.tri.simplices, m.tri.neighbors
        ks = np.arange(len(S)) if ks is None else np.asarray(ks, dtype=np.intp)
        tr = m._transforms()
        row, j = np.nonzero(N[ks] >= 0)  # each (triangle, neighbour) pair
        k = ks[row]
        nb = N[k, j]
        far = S[nb, np.argmax(N[nb] == k[:, None], axis=1)]  # the neighbour's vertex across the shared edge
        T, d = tr[k], m.T[far] - tr[k, 2]
        l0 = T[:, 0, 0] * d[:, 0] + T[:, 0, 1] * d[:, 1]  # the far pair's barycentric coordinates in triangle k
        l1 = T[:, 1, 0] * d[:, 0] + T[:, 1, 1] * d[:, 1]
        V = m.L[S[k]]
        guess = l0[:, None] * V[:, 0] + l1[:, None] * V[:, 1] + (1.0 - l0 - l1)[:, None] * V[:, 2]
        miss = np.hypot(*(guess - m.L[far]).T)
        total = np.bincount(row, weights=miss, minlength=len(ks))
        count = np.bincount(row, minlength=len(ks))
        return np.where(count > 0, total / np.maximum(count, 1), 0.0)

    def _line(self, t: NDArray[np.float64], k: int) -> tuple[NDArray[np.float64], Region]:
        """Linear interpolation of ``t`` on triangle ``k`` of the SC mapper's own triangulation (the barycentric
        mapper's triangles: the same Delaunay triangulation of the same pairs)."""
        m = self.scm
        assert m.tri is not None
        tr = m._transforms()[k]
        lam = tr[:2].dot(t - tr[2])
        verts = m.tri.simplices[k]
        return np.array([lam[0], lam[1], 1.0 - lam.sum()]) @ m.L[verts], tuple(int(m.ids[v]) for v in verts)

    def map_normalised(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], str, Region] | None:
        """``(l, method, region)`` for normalised teacher command ``t``, or None (module docstring)."""
        m = self.scm
        m._sync()
        k = m._simplex(t)
        if k < 0:
            return None
        if not self.holes()[k]:
            return self._as("barycentric", self._line(t, k))
        for quad, key in m._candidates_of(k):  # the SC mapper's own answer (ScmMapper.map_normalised), located once
            qt = m._transfer(quad, key)
            if qt is None:
                continue
            out = qt(t.reshape(1, 2), outside="nan")[0]
            if np.all(np.isfinite(out)):
                return out, "scm", tuple(int(m.ids[v]) for v in quad)
        return None

    @staticmethod
    def _as(method: str, got: tuple[NDArray[np.float64], Region]) -> tuple[NDArray[np.float64], str, Region]:
        """``(l, region)`` named by ``method``."""
        return got[0], method, got[1]

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], str, Region] | None]:
        """:meth:`map_normalised` of every row of ``P`` ``(n, 2)``: the triangles located in one pass, the SC map of
        the rows in big triangles together."""
        m = self.scm
        m._sync()
        res: list[tuple[NDArray[np.float64], str, Region] | None] = [None] * len(P)
        if m.tri is None or not len(P):
            return res
        K = m._simplices(P)
        holes = self.holes()
        big = [i for i, k in enumerate(K.tolist()) if k >= 0 and holes[k]]
        for i, k in enumerate(K.tolist()):
            if k >= 0 and not holes[k]:
                res[i] = self._as("barycentric", self._line(P[i], k))
        if big:
            for i, got in zip(big, m.map_many(P[big])):
                res[i] = None if got is None else (got[0], "scm", got[1])
        return res


def _longest_side(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """The longest side of each triangle of ``P`` ``(n, 3, 2)``."""
    d = P - P[:, [2, 0, 1]]
    return np.hypot(d[..., 0], d[..., 1]).max(axis=1)
