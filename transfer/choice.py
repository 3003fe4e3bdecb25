"""Which map serves a command inside the learned region: the SC map, or linear interpolation (docs/PAPER.md, "The
transfer's choice of map").

On the refined pairs a mission leaves (docs/PAPER.md, ``sim grid``) neither map is better everywhere: linear
interpolation on the triangle of pairs holding the command (:class:`transfer.mappers.BarycentricMapper`'s) is exact
where the learner's response is nearly affine across the triangle, which is where the pairs are dense and the triangles
small, and the SC map's conformal distortion is its error there (the map through two rectangles of different moduli is
not affine even where the pairs are); the SC map (:class:`transfer.mappers.ScmMapper`, paper Section 4) is the better
guess across a hole of the map, a big triangle whose three pairs say nothing of the response inside it and whose
quadrilateral bends the map by a fourth pair. :class:`MapChoice` decides per command from the pairs' geometry alone,
with no knowledge of the learner and no second map:

- the triangle of the SC mapper's own Delaunay triangulation holding the command (teacher domain, normalised);
- its longest side above :data:`HOLE`: it spans a hole: the SC map (``scm``), as the paper's mapper answers there
  (its best-shaped valid quadrilateral around the triangle), or no answer where the SC mapper has none (the policy
  then falls back as without the choice: the same line);
- else the line of that triangle (``barycentric``).

Pure: no I/O, no clock. Each triangle's size is computed once per triangulation, with the barycentric transforms the
mapper keeps; a command in a small triangle costs one dot product, one in a big triangle the SC map alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from transfer.mappers import Region, ScmMapper

#: a triangle whose longest teacher side exceeds this (normalised teacher units: about three cells of the default
#: 11 x 11 store) spans a hole of the map: the SC map serves it, the line every smaller one
HOLE = 0.28


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
        """Per triangle of the SC mapper's current triangulation: whether its longest teacher side exceeds
        :data:`HOLE` (computed for all at once, once per triangulation)."""
        m = self.scm
        if self._holes_of is not m.tri:
            if m.tri is None:
                self._holes = np.zeros(0, dtype=bool)
            else:
                P = m.T[m.tri.simplices]  # (n, 3, 2)
                d = P - P[:, [2, 0, 1]]
                self._holes = np.hypot(d[..., 0], d[..., 1]).max(axis=1) > HOLE
            self._holes_of = m.tri
        return self._holes

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
