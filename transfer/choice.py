"""Which map serves a command inside the learned region: the SC map, or linear interpolation (docs/PAPER.md, "The
transfer's choice of map").

On the refined pairs a mission leaves (docs/PAPER.md, ``sim grid``) neither map is better everywhere: the SC map
(:class:`transfer.mappers.ScmMapper`, paper Section 4) wins where a triangle of pairs spans a hole of the map (its
quadrilateral takes a fourth pair into account), and loses, by its conformal distortion, where the pairs are dense and
the learner's response nearly affine there, which linear interpolation on the triangle
(:class:`transfer.mappers.BarycentricMapper`'s) reproduces exactly. :class:`MapChoice` decides per command from what
the two maps themselves say, with no knowledge of the learner:

- the SC map ``s`` (the best-shaped quadrilateral's, as the paper's mapper picks it) and the linear map ``b`` of the
  triangle holding the command; their difference ``D = max |s - b|`` (normalised learner units);
- ``D`` within :data:`AGREE`: the maps agree, the response is locally affine: linear (``barycentric``);
- else the SC maps of every valid quadrilateral around the triangle (each completes it with another neighbour's pair):
  their spread (largest range over the axes) is how uncertain the SC map is there. ``scm`` when that spread is below
  :data:`TRUST` times ``D`` (the SC maps agree with each other better than with the line: the triangle misses
  curvature the fourth pairs see), else linear;
- one valid quadrilateral only (no spread to measure): ``scm`` only when ``D`` exceeds one grid cell of the learner
  (a triangle across a hole), else linear.

Pure: no I/O, no clock. The SC maps are the mapper's own, cached per quadrilateral; a command where the maps agree
costs one SC map and one linear interpolation; only a command where they disagree maps its other quadrilaterals.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from transfer.mappers import Region, ScmMapper

#: the SC and linear maps agree within this (normalised learner units: 2 % of the learner's range): linear
AGREE = 0.02
#: the SC map is trusted where the spread of its quadrilaterals' maps is below this share of its distance to the line
TRUST = 0.5


class MapChoice:
    """The SC map or linear interpolation, per command (module docstring). ``map_normalised`` returns ``(l, method,
    region)`` with ``method`` ``"scm"`` or ``"barycentric"``, or None where the SC mapper has no region (the policy
    falls back as without the choice)."""

    def __init__(self, scm: ScmMapper) -> None:
        self.scm = scm
        self.store = scm.store

    def _decide(self, t: NDArray[np.float64], k: int, s: tuple[NDArray[np.float64], Region] | None,
                b: tuple[NDArray[np.float64], Region] | None) -> tuple[NDArray[np.float64], str, Region] | None:
        """The choice for ``t`` in triangle ``k`` from its SC map ``s`` (None: no SC region) and its line ``b``."""
        if s is None or not np.all(np.isfinite(s[0])):
            return None
        if b is None or not np.all(np.isfinite(b[0])):
            return s[0], "scm", s[1]
        d = float(np.max(np.abs(s[0] - b[0])))
        if d <= AGREE:
            return b[0], "barycentric", b[1]
        outs = self._all_quads(t, k)
        if len(outs) < 2:
            one_cell = 1.0 / float(min(self.store.grid))
            return (s[0], "scm", s[1]) if d > one_cell else (b[0], "barycentric", b[1])
        spread = float(np.max(np.ptp(np.array(outs), axis=0)))
        return (s[0], "scm", s[1]) if spread < TRUST * d else (b[0], "barycentric", b[1])

    def _all_quads(self, t: NDArray[np.float64], k: int) -> list[NDArray[np.float64]]:
        """The SC map of ``t`` on every valid quadrilateral around its triangle ``k``."""
        m = self.scm
        outs = []
        for quad, key in m._candidates_of(k):
            qt = m._transfer(quad, key)
            if qt is None:
                continue
            out = qt(t.reshape(1, 2), outside="nan")[0]
            if np.all(np.isfinite(out)):
                outs.append(out)
        return outs

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
        """``(l, method, region)`` for normalised teacher command ``t``, or None (no SC region)."""
        m = self.scm
        m._sync()
        k = m._simplex(t)
        if k < 0:
            return None
        for quad, key in m._candidates_of(k):  # the SC mapper's own answer (ScmMapper.map_normalised), located once
            qt = m._transfer(quad, key)
            if qt is None:
                continue
            out = qt(t.reshape(1, 2), outside="nan")[0]
            if np.all(np.isfinite(out)):
                return self._decide(t, k, (out, tuple(int(m.ids[v]) for v in quad)), self._line(t, k))
        return None

    def map_many(self, P: NDArray[np.float64]) -> list[tuple[NDArray[np.float64], str, Region] | None]:
        """:meth:`map_normalised` of every row of ``P`` ``(n, 2)``: the SC and linear maps of all rows together."""
        S = self.scm.map_many(P)
        K = self.scm._simplices(P) if any(s is not None for s in S) else np.full(len(P), -1)
        return [None if s is None else self._decide(p, int(k), s, self._line(p, int(k))) for p, s, k in zip(P, S, K)]
