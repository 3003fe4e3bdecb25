"""Schwarz-Christoffel rectangle maps of polygons, and the teacher -> learner transfer built on them.

``RectangleMap(vertices, corners)`` is the conformal map f of the rectangle [-K, K] x [0, K'] onto the polygon,
corner vertices to rectangle corners, computed as in the SC Toolbox's ``rectmap``: f = F o R with
R(u) = log(sn(u | m)) / pi onto the strip {0 <= Im s <= 1} and F the strip SC map (docs/ARCHITECTURE.md section 9).

The user-facing coordinates are those of the *unit square*: the rectangle scaled per axis so that corners[0]
-> 0, corners[1] -> 1, corners[2] -> 1 + 1j, corners[3] -> 1j. The conformal image is ``modulus * a + 1j * b``.

Numerical choices (each re-derived and tested, see tests/unit/transfer/scm/test_rectmap.py):
- Labelling: internally the first side is a long side of the rectangle (so L is not exponentially small) and the
  vertex preceding the first corner is not a straight angle; both are exact 90/180 degree rotations of the unit
  square, undone on output.
- Prevertices: L = exp(y0); the prevertices between two corners are parametrised by the logarithms of their gaps
  (normalised to the side), those on the strip's two ends through X = exp(+-pi (s - s_end)) in (-1, 1), so every
  y in R^(N-3) is a valid ordered configuration. N = 4 has the single unknown L (Newton on log L).
- Quadrature: compound Gauss-Jacobi (rules by Golub-Welsch, compiled), pieces no longer than the distance to the
  nearest other prevertex.
- Corner-local evaluation: a point near a rectangle corner is carried as (corner, offset) end to end, its strip
  offset computed from cd(delta) - 1 without cancellation (docs/ARCHITECTURE.md section 9); Newton steps near a
  corner are taken in the corner's power variable. Round trips therefore hold near acute vertices too, down to
  what a float64 unit-square coordinate can hold (see ``to_unit_square``).
- Inverse: start from the nearest of a small table of forward images (built on the first inverse call), then a
  safeguarded Newton that accepts only finite, improving steps.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import scipy.optimize
import scipy.special
from numpy.typing import ArrayLike, NDArray

from transfer.scm import _evaluate, _parameters, _polygon, _quadrature
from transfer.scm.geometry import as_complex, check_corners, check_polygon, turning_exponents

#: unit-square images of the four user corners
SQUARE_CORNERS = np.array([0.0, 1.0, 1.0 + 1.0j, 1.0j], dtype=np.complex128)
_ROT = np.array([1.0, 1.0j, -1.0, -1.0j], dtype=np.complex128)  # i**r
_NEAR_CORNER = 0.2  # unit-square distance below which a point is carried relative to its corner
_SIG4 = np.array([1.0, 1.0, -1.0, -1.0])
_CROWDING = 1e-7  # smallest prevertex separation that float64 strip coordinates resolve well enough


def _min_separation(z: NDArray[np.complex128]) -> float:
    """The least distance between two of the prevertices ``z`` (NaN if any is NaN), numpy's same arithmetic over
    the upper triangle's indices made once per polygon size (``np.triu_indices`` cost more than the distances)."""
    return np.abs(z[:, None] - z[None, :])[_upper(z.size)].min()


@functools.lru_cache(maxsize=16)
def _upper(n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``np.triu_indices(n, 1)``, read-only."""
    i, j = np.triu_indices(n, 1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


class RectangleMap:
    """Conformal map of a polygon onto the unit square via its SC rectangle map (see the module docstring).

    Parameters
    ----------
    vertices: N >= 4 vertices, counter-clockwise, as complex numbers or an (N, 2) float array.
    corners: the 4 vertex indices (distinct, increasing) that go to the unit square's corners 0, 1, 1+1j, 1j.
    tol: accuracy target of the parameter problem and of Newton (relative to the polygon's size).
    """

    def __init__(self, vertices: ArrayLike, corners: Sequence[int] = (0, 1, 2, 3), *, tol: float = 1e-13) -> None:
        w = check_polygon(vertices)
        cs = check_corners(corners, w.size)
        beta_all = turning_exponents(w)
        for k, c in enumerate(cs):
            if w.size == 4 and abs(beta_all[c]) < 1e-12:  # a quadrilateral with a straight corner is a triangle
                raise ValueError(f"corner {k} (vertex {c}) has a straight angle: it cannot be a rectangle corner")
        self.vertices = w
        self.corners = cs
        self.tol = float(tol)
        self.scale = float(np.max(np.abs(w - w.mean())))
        lens = self._label(w, cs, beta_all)
        y = self._solve_parameters(lens)
        self._set_rectangle(float(math.exp(y[0])))

    def _label(self, w: NDArray[np.complex128], cs: tuple[int, ...], beta_all: NDArray[np.float64]) -> list[float]:
        """Rotate the corner list so that the first side is long and the vertex before it not straight (the
        toolbox's convention); set the internal vertex order, corner indices, angles and quadrature rules.
        Returns the boundary length between consecutive corners (user order)."""
        n = w.size
        arc = np.abs(np.concatenate((w[1:], w[:1])) - w)

        def chain(a: int, b: int) -> float:
            idx = [(a + i) % n for i in range((b - a) % n)]
            return float(arc[idx].sum())

        lens = [chain(cs[i], cs[(i + 1) % 4]) for i in range(4)]
        r_long = 0 if lens[0] + lens[2] >= lens[1] + lens[3] else 1
        for r in (r_long, r_long + 2, 1 - r_long, 3 - r_long):
            if abs(beta_all[(cs[r] - 1) % n]) >= 1e-12:
                break  # the vertex preceding the first corner must not be straight (the toolbox's convention)
        else:
            raise ValueError("every corner is preceded by a straight angle: the polygon is degenerate")
        self._r = r % 4
        start = cs[self._r]
        self._order = (np.arange(n) + start) % n  # internal index -> user vertex index
        self._ic = np.array([(cs[(self._r + k) % 4] - start) % n for k in range(4)], dtype=np.int64)  # ic[0] = 0
        self._w = w[self._order]
        self._beta = beta_all[self._order]
        self._qx, self._qw, self._lx, self._lw = _quadrature.jacobi_table(self._beta, 14)
        return lens

    def _solve_parameters(self, lens: list[float]) -> NDArray[np.float64]:
        """The parameter problem: prevertices whose side integrals have the polygon's side ratios; sets the
        prevertices and the map's constant. Refuses crowded prevertices by name."""
        wi, beta, ic, n = self._w, self._beta, self._ic, self._w.size
        self._groups = (
            ic[1] - 1,  # bottom side between corners 0 and 1
            ic[2] - ic[1] - 1,  # right end
            ic[3] - ic[2] - 1,  # top side
            n - ic[3] - 1,  # left end
        )
        ratios = np.log(np.abs(wi[2 : n - 1] - wi[1 : n - 2]) / abs(wi[1] - wi[0]))  # sides 1..n-3 vs side 0
        length = 0.5 * (lens[self._r] + lens[(self._r + 2) % 4])
        width = 0.5 * (lens[(self._r + 1) % 4] + lens[(self._r + 3) % 4])
        L0 = max(min(length / width, 100.0) - math.log(4.0) / math.pi, 0.05)

        if n == 4:  # the quadrilateral of the control path: its one unknown, log L, solved in compiled code
            args = (beta, _SIG4, self._qx, self._qw, self._lx, self._lw, float(ratios[0]))
            y0 = math.log(L0)  # the guess of _initial_guess, which has nothing else to place
            y1, _, ok = _parameters.quad_newton(y0, *args, 1e-2 * self.tol)
            y = np.array([y1]) if ok else self._solve_bracketed(
                lambda y: np.array([_parameters.quad_residual(float(y[0]), *args)]), y0, 10.0 * self.tol)
        else:

            def residual(y: NDArray[np.float64]) -> NDArray[np.float64]:
                z, sig = self._prevertices(y)
                I = _quadrature.side_integrals(z, beta, sig, self._qx, self._qw, self._lx, self._lw, n - 2)
                with np.errstate(divide="ignore", invalid="ignore"):
                    F = np.log(np.abs(I[1:])) - np.log(np.abs(I[0])) - ratios
                # a configuration where quadrature breaks down (crowding) is far from the solution: say so finitely
                return np.where(np.isfinite(F), F, 1e3)

            y = self._solve(residual, self._initial_guess(L0, True))
        z, sig = self._prevertices(y)
        sep = _min_separation(z)
        if sep < _CROWDING:
            # prevertices this close cannot be told apart in float64 strip coordinates: the map would be
            # wrong at the 1e-9 level near them. The SC Toolbox shares this limit; re-choose the region instead.
            raise ValueError(f"SC prevertices crowd (separation {sep:.1e} < {_CROWDING:.0e}): polygon too elongated "
                             "between its corners for an accurate rectangle map")
        self._z, self._sig = z, sig
        I0 = _quadrature.side_integrals(z, beta, sig, self._qx, self._qw, self._lx, self._lw, 1)[0]
        self._c = complex((wi[1] - wi[0]) / I0)
        return y

    def _set_rectangle(self, L: float) -> None:
        """The rectangle of strip length L: elliptic parameter, K and K', the conformal modulus."""
        self.L = L
        m = math.exp(-2.0 * math.pi * L)
        if L > 10.0:
            K, Kp = math.pi / 2.0, math.pi * L + math.log(4.0)
        else:
            K, Kp = float(scipy.special.ellipk(m)), float(scipy.special.ellipkm1(m))
        self._m, self._kp, self._K, self._Kp = m, math.sqrt(-math.expm1(-2.0 * math.pi * L)), K, Kp
        self._alpha_c = self._beta[self._ic] + 1.0
        self._radius = 0.25 * min(2.0 * K, Kp)
        self._table: tuple[NDArray[np.complex128], NDArray[np.complex128]] | None = None
        internal_mod = Kp / (2.0 * K)
        self.modulus = internal_mod if self._r % 2 == 0 else 1.0 / internal_mod

    # ------------------------------------------------------------------------------------------ construction
    def _prevertices(self, y: NDArray[np.float64]) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
        """Strip prevertices (internal order) from the unconstrained parameters y (see the module docstring)."""
        n = self._w.size
        ic = self._ic
        L = math.exp(min(y[0], 700.0 / (2 * math.pi)))
        if n == 4:  # the quadrilateral: only the corners, the common case on the control path
            return np.array([0.0, L, L + 1j, 1j]), _SIG4
        z = np.empty(n, dtype=np.complex128)
        z[ic[0]], z[ic[1]], z[ic[2]], z[ic[3]] = 0.0, L, L + 1j, 1j
        pos = 1

        def fractions(p: int) -> NDArray[np.float64]:
            nonlocal pos
            g = np.concatenate(([1.0], np.exp(np.clip(y[pos : pos + p], -300, 300))))
            pos += p
            return np.cumsum(g)[:p] / g.sum()

        pb, pr, pt, pl = self._groups
        f = fractions(pb)
        z[1 : ic[1]] = L * f
        f = fractions(pr)
        X = 1.0 - 2.0 * f  # decreasing from 1 to -1 along the right end
        with np.errstate(divide="ignore"):
            z[ic[1] + 1 : ic[2]] = np.where(X > 0, L - np.log(np.abs(X)) / np.pi, L - np.log(np.abs(X)) / np.pi + 1j)
        f = fractions(pt)
        z[ic[2] + 1 : ic[3]] = L * (1.0 - f) + 1j
        f = fractions(pl)
        X = -1.0 + 2.0 * f  # increasing from -1 to 1 along the left end
        with np.errstate(divide="ignore"):
            z[ic[3] + 1 :] = np.where(X > 0, np.log(np.abs(X)) / np.pi, np.log(np.abs(X)) / np.pi + 1j)
        sig = np.where(z.imag == 0.0, 1.0, -1.0)
        return z, sig

    def _initial_guess(self, L0: float, ends_on_long_edges: bool = True) -> NDArray[np.float64]:
        """Long sides evenly spaced on [0, L0]; end vertices continue the spacing past the corners along one edge
        (the SC Toolbox's guess: left end on the top edge, right end on the bottom edge, or the other way round),
        never at the strip end itself."""
        pb, pr, pt, pl = self._groups
        h = L0 / (max(pb, pt) + 1)

        def gaps_y(f: NDArray[np.float64]) -> NDArray[np.float64]:
            g = np.diff(np.concatenate(([0.0], f, [1.0])))
            return np.log(g[1:] / g[0])

        def right_end(p: int, bottom: bool) -> NDArray[np.float64]:
            # X = 1 - 2 f decreases from 1 (corner 1) through 0 (the strip end) to -1 (corner 2)
            k = np.arange(1, p + 1)
            X = np.exp(-math.pi * h * k) if bottom else -np.exp(-math.pi * h * (p + 1 - k))
            return gaps_y((1.0 - X) / 2.0)

        def left_end(p: int, top: bool) -> NDArray[np.float64]:
            # X = -1 + 2 f increases from -1 (corner 3) through 0 (the strip end) to 1 (corner 0)
            k = np.arange(1, p + 1)
            X = -np.exp(-math.pi * h * k) if top else np.exp(-math.pi * h * (p + 1 - k))
            return gaps_y((X + 1.0) / 2.0)

        parts = [np.array([math.log(L0)])]
        parts.append(gaps_y(np.arange(1, pb + 1) / (pb + 1)))
        parts.append(right_end(pr, ends_on_long_edges))
        parts.append(gaps_y(np.arange(1, pt + 1) / (pt + 1)))
        parts.append(left_end(pl, ends_on_long_edges))
        return np.concatenate(parts)

    def _solve(self, residual, y0: NDArray[np.float64]) -> NDArray[np.float64]:
        """The parameter problem of a polygon with more than four vertices (MINPACK hybrd from a ladder of starts;
        the quadrilateral's one unknown is solved by :func:`~transfer.scm._parameters.quad_newton`)."""
        best, best_err = y0, np.inf
        L0 = math.exp(y0[0])
        # the guess's L0 comes from the polygon's side lengths, which a reflex corner can make far off: retry from
        # a ladder of strip lengths around it before giving up (each start is a few hundred residual evaluations)
        ladder = [f * L0 for f in (0.5, 2.0, 0.25, 4.0, 0.125, 8.0, 1 / 16, 16.0)]
        starts = [y0, self._initial_guess(L0, False), *(self._initial_guess(L, True) for L in ladder)]
        for start in starts:
            sol = scipy.optimize.root(residual, start, method="hybr", options={"xtol": 1e-14})
            F = residual(sol.x)
            err = float(np.max(np.abs(F))) if np.all(np.isfinite(F)) else np.inf
            if err > 1e-10:  # polish or rescue with a bounded least-squares solve
                ls = scipy.optimize.least_squares(residual, sol.x if err < np.inf else start, xtol=1e-15,
                                                  ftol=1e-15, gtol=1e-15, max_nfev=400)
                F2 = residual(ls.x)
                err2 = float(np.max(np.abs(F2))) if np.all(np.isfinite(F2)) else np.inf
                if err2 < err:
                    sol.x, err = ls.x, err2
            if err < best_err:
                best, best_err = sol.x, err
            if best_err <= 1e-8:
                return best
        z, _ = self._prevertices(best)
        sep = _min_separation(z)
        if sep < 1e3 * _CROWDING:  # the usual reason: crowding makes the side integrals too inaccurate to solve
            raise ValueError(f"SC prevertices crowd (separation {sep:.1e}): polygon too elongated between its "
                             f"corners for an accurate rectangle map (parameter residual {best_err:.1e})")
        raise ValueError(f"SC parameter problem did not converge (residual {best_err:.1e})")

    @staticmethod
    def _solve_bracketed(residual, y0: float, accept: float) -> NDArray[np.float64]:
        """The quadrilateral's one unknown (log L) when Newton did not converge: a sign change of the residual
        searched outwards from the guess, then Brent's method on it. A few dozen residual evaluations either way, so
        a region that has no accurate map (a sliver whose corners are almost collinear) is refused at once instead
        of after a multi-start search."""

        def f(y: float) -> float:
            F = float(residual(np.array([y]))[0])
            return F if math.isfinite(F) else math.nan

        lo = hi = y0
        f_lo = f_hi = f(y0)
        for step in (0.25, 0.5, 1.0, 2.0, 4.0, 8.0):
            if math.isfinite(f_lo) and math.isfinite(f_hi) and f_lo * f_hi <= 0.0:
                break
            lo, hi = y0 - step, y0 + step
            f_lo, f_hi = f(lo), f(hi)
        if math.isfinite(f_lo) and math.isfinite(f_hi) and f_lo * f_hi <= 0.0:
            y = float(scipy.optimize.brentq(f, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=200))
            F = f(y)
            if math.isfinite(F) and abs(F) < accept:
                return np.array([y])
            raise ValueError(f"SC parameter problem did not converge (residual {F:.1e}): the quadrilateral is too "
                             "thin for an accurate rectangle map")
        raise ValueError("SC parameter problem has no solution near the guess: the quadrilateral is too thin for an "
                         "accurate rectangle map")

    def _args(self) -> tuple:
        return (
            self._m, self._kp, self._K, self._Kp, self._z, self._beta, self._sig, self._qx, self._qw, self._lx,
            self._lw, self._w, self._c, self._ic,
        )

    # -------------------------------------------------------------------------------- unit-square <-> internal
    def _square_to_internal(self, p: NDArray[np.complex128]) -> tuple[NDArray[np.int64], NDArray[np.complex128]]:
        """User unit-square points -> internal (corner, delta); near a corner the offset is taken exactly."""
        r = self._r
        K, Kp = self._K, self._Kp
        dist = np.abs(p[:, None] - SQUARE_CORNERS[None, :])
        uc = np.argmin(dist, axis=1)
        near = dist[np.arange(p.size), uc] < _NEAR_CORNER
        cs = np.where(near, (uc - r) % 4, -1).astype(np.int64)
        delta_user = p - SQUARE_CORNERS[uc]
        dprime = delta_user / _ROT[r]
        d_corner = -2.0 * K * dprime.imag + 1j * Kp * dprime.real
        pprime = (p - SQUARE_CORNERS[r]) / _ROT[r]
        u_abs = K - 2.0 * K * pprime.imag + 1j * Kp * pprime.real
        return cs, np.where(near, d_corner, u_abs)

    def _internal_to_square(self, cs: NDArray[np.int64], ds: NDArray[np.complex128]) -> NDArray[np.complex128]:
        r = self._r
        K, Kp = self._K, self._Kp
        dprime = ds.imag / Kp - 1j * ds.real / (2.0 * K)
        corner_part = SQUARE_CORNERS[(cs + r) % 4] + _ROT[r] * dprime
        pprime = ds.imag / Kp + 1j * (K - ds.real) / (2.0 * K)
        abs_part = SQUARE_CORNERS[r] + _ROT[r] * pprime
        return np.where(cs >= 0, corner_part, abs_part)

    # ------------------------------------------------------------------------------------------- evaluation
    def _forward_internal(self, cs: NDArray[np.int64], ds: NDArray[np.complex128]) -> NDArray[np.complex128]:
        return _evaluate.forward_many(cs, ds, *self._args())

    def _ensure_table(self) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        if self._table is None:
            g = np.array([0.0, 0.03, 0.12, 0.3, 0.5, 0.7, 0.88, 0.97, 1.0])
            A, B = np.meshgrid(g, g)
            keep = ~(((A == 0) | (A == 1)) & ((B == 0) | (B == 1)))
            a, b = A[keep], B[keep]
            u = self._K - 2.0 * self._K * b + 1j * self._Kp * a
            tw = self._forward_internal(np.full(u.size, -1, dtype=np.int64), u.astype(np.complex128))
            self._table = (u.astype(np.complex128), tw)
        return self._table

    def _inverse_internal(self, w: NDArray[np.complex128]) -> tuple[NDArray[np.int64], NDArray[np.complex128],
                                                                    NDArray[np.float64]]:
        tu, tw = self._ensure_table()
        return _evaluate.inverse_many(
            w, tu, tw, *self._args(), self._alpha_c, self.tol * max(self.scale, 1e-300), self._radius
        )

    def _ktuple(self, inverse: bool = True) -> tuple:
        """Everything the compiled transfer kernel needs about this map; the inverse's start table only when the
        map will be inverted (the learner side of a transfer is only evaluated forward)."""
        if inverse:
            tu, tw = self._ensure_table()
        else:
            tu = tw = np.zeros(1, dtype=np.complex128)
        return (
            self._m, self._kp, self._K, self._Kp, self._z, self._beta, self._sig, self._qx, self._qw, self._lx,
            self._lw, self._w, self._c, self._ic, self._alpha_c, self.tol * max(self.scale, 1e-300), self._radius,
            self._r, tu, tw, self.vertices, 1e-10 * max(self.scale, 1e-300),
        )

    def _inside(self, w: NDArray[np.complex128]) -> NDArray[np.bool_]:
        return _polygon.points_in_polygon(w, self.vertices, 1e-10 * max(self.scale, 1e-300))

    def to_unit_square(self, w: ArrayLike, *, outside: str = "raise") -> NDArray[np.complex128]:
        """Polygon points (complex, any shape) -> unit-square points.

        A point outside the polygon (beyond 1e-10 x its size) raises ValueError, or with ``outside="nan"`` maps
        to NaN. Near corners[1..3] the result is a float64 near 1, 1+1j or 1j, so it holds the offset only to
        ~1e-16 absolute; for a vertex of interior angle alpha*pi the round trip is then exact to about
        size * (1e-16 / d^(1/(2 alpha)))  * d at distance d: fine for alpha >= 1/4 (45 degrees) at d >= 1e-6.
        :class:`QuadTransfer` carries the exact offsets instead.
        """
        cs, ds, ok = self._to_parts(w, outside)
        out = self._internal_to_square(cs, ds)
        out[~ok] = np.nan
        return out.reshape(np.shape(np.asarray(w)))

    def _to_parts(self, w: ArrayLike, outside: str) -> tuple[NDArray[np.int64], NDArray[np.complex128],
                                                              NDArray[np.bool_]]:
        if outside not in ("raise", "nan"):
            raise ValueError(f"outside must be 'raise' or 'nan', not {outside!r}")
        z = np.asarray(w, dtype=np.complex128).ravel()
        finite = np.isfinite(z)
        if outside == "raise" and not np.all(finite):
            raise ValueError("points contain non-finite numbers (NaN or inf)")
        inside = np.zeros(z.size, dtype=bool)
        inside[finite] = self._inside(z[finite])
        if outside == "raise" and not np.all(inside):
            bad = z[~inside][0]
            raise ValueError(f"point {bad} lies outside the polygon; it is not mapped")
        cs = np.full(z.size, -1, dtype=np.int64)
        ds = np.full(z.size, np.nan + 0j, dtype=np.complex128)
        if np.any(inside):
            c_in, d_in, _ = self._inverse_internal(z[inside])
            cs[inside], ds[inside] = c_in, d_in
        return cs, ds, inside

    def from_unit_square(self, s: ArrayLike, *, outside: str = "raise") -> NDArray[np.complex128]:
        """Unit-square points (complex, any shape) -> polygon points; points outside the closed unit square raise
        ValueError (or give NaN with ``outside="nan"``)."""
        p = np.asarray(s, dtype=np.complex128)
        return self._from_parts_user(p.ravel(), outside).reshape(p.shape)

    def _from_parts_user(self, p: NDArray[np.complex128], outside: str) -> NDArray[np.complex128]:
        if outside not in ("raise", "nan"):
            raise ValueError(f"outside must be 'raise' or 'nan', not {outside!r}")
        eps = 1e-12
        ok = np.isfinite(p) & (p.real >= -eps) & (p.real <= 1 + eps) & (p.imag >= -eps) & (p.imag <= 1 + eps)
        if outside == "raise" and not np.all(ok):
            raise ValueError(f"unit-square point {p[~ok][0]} lies outside the unit square")
        pc = np.clip(p.real, 0.0, 1.0) + 1j * np.clip(p.imag, 0.0, 1.0)
        pc[~ok] = 0.5 + 0.5j
        cs, ds = self._square_to_internal(pc)
        out = self._forward_internal(cs, ds)
        out[~ok] = np.nan
        return out



class QuadTransfer:
    """Teacher polygon -> unit square -> learner polygon, vertex k of both sides being command pair k.

    ``t(u_T)`` accepts complex numbers or an (..., 2) float array and returns the same form. Teacher points outside
    the teacher polygon raise ValueError (``outside="nan"`` gives NaN instead). Near a corner the unit-square
    offset is handed over exactly (not rounded to a float next to 1), so accuracy near acute vertices is kept.
    """

    def __init__(
        self, teacher_vertices: ArrayLike, learner_vertices: ArrayLike, corners: Sequence[int] = (0, 1, 2, 3)
    ) -> None:
        self.teacher = RectangleMap(teacher_vertices, corners)  # each validates its polygon
        self.learner = RectangleMap(learner_vertices, corners)
        nt, nl = self.teacher.vertices.size, self.learner.vertices.size
        if nt != nl:
            raise ValueError(f"teacher and learner polygons need the same number of vertices ({nt} != {nl})")
        self._kt: tuple | None = None

    def __call__(self, u_T: ArrayLike, *, outside: str = "raise") -> NDArray:
        if outside not in ("raise", "nan"):
            raise ValueError(f"outside must be 'raise' or 'nan', not {outside!r}")
        a = np.asarray(u_T)
        pairs = not np.iscomplexobj(a) and a.ndim >= 1 and a.shape[-1] == 2
        z = as_complex(a) if pairs else a.astype(np.complex128)
        shape = z.shape
        flat = np.ascontiguousarray(z.ravel())
        if outside == "raise" and not np.all(np.isfinite(flat)):
            raise ValueError("points contain non-finite numbers (NaN or inf)")
        if self._kt is None:
            self._kt = (self.teacher._ktuple(), self.learner._ktuple(inverse=False))
        safe = np.where(np.isfinite(flat), flat, self.teacher.vertices[0] * 0 + 1e300)
        out = _evaluate.transfer_many(safe, self._kt[0], self._kt[1], _NEAR_CORNER)
        if outside == "raise" and not np.all(np.isfinite(out)):
            bad = flat[~np.isfinite(out)][0]
            raise ValueError(f"point {bad} lies outside the teacher polygon; it is not mapped")
        out = out.reshape(shape)
        if pairs:
            return np.stack([out.real, out.imag], axis=-1)
        return out
