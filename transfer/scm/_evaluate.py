"""Compiled evaluation of the SC rectangle map (numba, cached on disk): rectangle <-> strip <-> polygon, forward
and inverse over many points, and the fused teacher -> learner transfer.

A departure from the SC Toolbox (docs/ARCHITECTURE.md section 9): corner-local evaluation, a point near a rectangle
corner carried as the corner plus an offset so that no digits are lost to cancellation. The prevertices and
quadrature tables come from ``rectmap.py``'s parameter solve (``_parameters``, ``_quadrature``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from transfer.scm._ellipj import ellipjc
from transfer.scm._polygon import points_in_polygon
from transfer.scm._quadrature import _min_dist, log_fprime_at, quad_from
from transfer.scm._scalar import EPS, PI, _sdiv

# -------------------------------------------------------------------------------- rectangle <-> strip <-> polygon
# Rectangle [-K, K] x [0, K'] ; internal corners 0..3 at K, K + iK', -K + iK', -K ; strip images 0, L, L + i, i.
# A rectangle point is carried as (corner, delta): u = U_c + delta for corner c in 0..3, or u = delta for c = -1.


@njit(cache=True, error_model="numpy")
def corner_u(c: int, K: float, Kp: float) -> complex:
    if c == 0:
        return K + 0j
    if c == 1:
        return K + 1j * Kp
    if c == 2:
        return -K + 1j * Kp
    return -K + 0j


@njit(cache=True, error_model="numpy")
def _log1p_c(e: complex) -> complex:
    """log(1 + e) for complex e without cancellation."""
    re = e.real
    im = e.imag
    return 0.5 * math.log1p(2.0 * re + re * re + im * im) + 1j * math.atan2(im, 1.0 + re)


@njit(cache=True, error_model="numpy")
def rect_to_strip(c: int, delta: complex, m: float, kp: float, K: float, Kp: float) -> tuple[int, complex, complex]:
    """Strip point of a rectangle point and ds/du. Returns (k, D, dsdu): s = z_k + D with k the strip corner index
    (0..3, exact offset) when c >= 0, or k = -1 and D = s (absolute) otherwise."""
    if c >= 0:
        sn, cn, dn = ellipjc(delta, m, kp, Kp)
        omm = kp * kp
        e = _sdiv(-omm * sn * sn, dn * (cn + dn))  # cd(delta) - 1 without cancellation
        sgn = 1.0 if (c == 0 or c == 3) else -1.0
        D = sgn * _log1p_c(e) / PI
        dsdu = _sdiv(-sgn * omm * sn, PI * cn * dn)
        # keep the point inside the closed strip (the offset from a bottom corner has Im >= 0, top corner Im <= 0)
        if c == 0 or c == 1:
            if D.imag < 0.0:
                D = D.real + 0j
        else:
            if D.imag > 0.0:
                D = D.real + 0j
        return c, D, dsdu
    u = delta
    # the rectangle's bottom and top midpoints go to the strip ends: nudge them inside
    if abs(u) < 2.0 * EPS:
        u = u + 100.0 * EPS
    if abs(u - 1j * Kp) < 2.0 * EPS * max(1.0, Kp):
        u = u - 100.0 * EPS * 1j * Kp
    sn, cn, dn = ellipjc(u, m, kp, Kp)
    if sn.imag < 0.0:
        sn = sn.real + 0j
    s = np.log(sn) / PI
    if s.imag < 0.0:
        s = s.real + 0j
    if s.imag > 1.0:
        s = s.real + 1j
    dsdu = _sdiv(cn * dn, PI * sn)
    return -1, s, dsdu


@njit(cache=True, error_model="numpy")
def forward_one(
    c: int, delta: complex, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx
) -> tuple[complex, complex]:
    """Polygon point and derivative f'(u) of one rectangle point (c, delta)."""
    k, D, dsdu = rect_to_strip(c, delta, m, kp, K, Kp)
    if k >= 0:
        v = corner_vtx[k]
        if _min_dist(z[v] + D, z, v) < abs(D):
            # another prevertex is nearer than the corner: integrate from that one (no straight path past it)
            k = -1
            D = z[v] + D
    if k >= 0:
        pass
    else:
        s = D
        v = 0
        best = np.inf
        for j in range(z.shape[0]):
            dj = abs(s - z[j])
            if dj < best:
                best = dj
                v = j
        D = s - z[v]
    if D == 0.0:
        return w[v], 0.0 + 0.0j
    val = w[v] + cc * quad_from(v, D, z, beta, sig, qx, qw, lx, lw)
    deriv = cc * np.exp(log_fprime_at(z, beta, sig, v, D)) * dsdu
    return val, deriv


@njit(cache=True, error_model="numpy")
def _nearest_corner(u: complex, K: float, Kp: float, radius: float) -> int:
    best = -1
    bd = radius
    for c in range(4):
        d = abs(u - corner_u(c, K, Kp))
        if d < bd:
            bd = d
            best = c
    return best


_INTO = np.array([-1.0 + 1.0j, -1.0 - 1.0j, 1.0 - 1.0j, 1.0 + 1.0j]) / math.sqrt(2.0)  # into the rectangle


@njit(cache=True, error_model="numpy")
def _project(u: complex, K: float, Kp: float) -> complex:
    return min(max(u.real, -K), K) + 1j * min(max(u.imag, 0.0), Kp)


@njit(cache=True, error_model="numpy")
def _project_delta(c: int, d: complex, K: float, Kp: float) -> complex:
    """Keep corner offset d inside the rectangle seen from corner c."""
    re = d.real
    im = d.imag
    if c == 0 or c == 1:
        re = min(max(re, -2.0 * K), 0.0)
    else:
        re = min(max(re, 0.0), 2.0 * K)
    if c == 0 or c == 3:
        im = min(max(im, 0.0), Kp)
    else:
        im = min(max(im, -Kp), 0.0)
    return re + 1j * im


@njit(cache=True, error_model="numpy")
def inverse_one(
    wp: complex, c0: int, d0: complex, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx, alpha_c,
    tol: float, radius: float
) -> tuple[int, complex, float]:
    """Newton for f(u) = wp from the start (c0, d0); near a corner in the corner's local power variable.

    Returns (c, delta, |residual|). Steps are accepted only when finite and improving (step halving)."""
    c = c0
    d = d0
    val, der = forward_one(c, d, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx)
    F = wp - val
    r = abs(F)
    for _ in range(60):
        if r <= tol:
            break
        # choose the representation: near a corner work in its offset
        u = corner_u(c, K, Kp) + d if c >= 0 else d
        cn_ = _nearest_corner(u, K, Kp, radius)
        if cn_ != c:
            c = cn_
            d = u - corner_u(c, K, Kp) if c >= 0 else u
            if c >= 0 and d == 0.0:
                d = 1e-8 * radius * _INTO[c]
            # the residual must be judged in the representation the steps are taken in: next to a corner the
            # absolute evaluation is off by ~size * eps^alpha, which would pass for an improvement
            val, der = forward_one(c, d, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx)
            F = wp - val
            r = abs(F)
        elif c >= 0 and d == 0.0:
            # exactly on the corner, where f' vanishes or blows up: step a little way into the rectangle
            d = 1e-8 * radius * _INTO[c]
            val, der = forward_one(c, d, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx)
            F = wp - val
            r = abs(F)
        improved = False
        lam = 1.0
        for _h in range(40):
            if c >= 0 and d != 0.0 and der != 0.0 and np.isfinite(der.real) and np.isfinite(der.imag):
                p = 2.0 * alpha_c[c]
                ratio = 1.0 + lam * p * _sdiv(F, der * d)
                dn_ = d * np.exp(np.log(ratio) / p) if ratio != 0.0 else d * 0.5
                dn_ = _project_delta(c, dn_, K, Kp)
                cn2 = c
            else:
                if der == 0.0 or not (np.isfinite(der.real) and np.isfinite(der.imag)):
                    # exactly on a corner: nudge toward the centre
                    uc = u + 1e-9 * (0.5j * Kp - u)
                    dn_ = uc
                else:
                    dn_ = _project(u + lam * _sdiv(F, der), K, Kp)
                cn2 = -1
            if not (np.isfinite(dn_.real) and np.isfinite(dn_.imag)):
                lam *= 0.5
                continue
            v2, d2 = forward_one(cn2, dn_, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx)
            F2 = wp - v2
            r2 = abs(F2)
            if np.isfinite(r2) and r2 < r:
                c, d, val, der, F, r = cn2, dn_, v2, d2, F2, r2
                improved = True
                break
            lam *= 0.5
        if not improved:
            break
    return c, d, r


@njit(cache=True, error_model="numpy")
def forward_many(cs, ds, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx) -> np.ndarray:
    out = np.empty(ds.shape[0], dtype=np.complex128)
    for i in range(ds.shape[0]):
        out[i] = forward_one(cs[i], ds[i], m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx)[0]
    return out


@njit(cache=True, error_model="numpy")
def inverse_many(
    wps, table_u, table_w, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx, alpha_c, tol, radius
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse map of many points: start from the nearest tabulated image (or the vertex itself), then Newton."""
    n = wps.shape[0]
    cs = np.empty(n, dtype=np.int64)
    ds = np.empty(n, dtype=np.complex128)
    rs = np.empty(n)
    nv = w.shape[0]
    for i in range(n):
        wp = wps[i]
        # exact vertex hits
        hit = -1
        for c in range(4):
            if wp == w[corner_vtx[c]]:
                hit = c
        if hit >= 0:
            cs[i] = hit
            ds[i] = 0.0
            rs[i] = 0.0
            continue
        best = 0
        bd = np.inf
        for t in range(table_w.shape[0]):
            dt = abs(table_w[t] - wp)
            if dt < bd:
                bd = dt
                best = t
        u0 = table_u[best]
        c0 = _nearest_corner(u0, K, Kp, radius)
        d0 = u0 - corner_u(c0, K, Kp) if c0 >= 0 else u0
        # a point very close to a corner vertex: start from the corner's local power law
        for c in range(4):
            dv = abs(wp - w[corner_vtx[c]])
            if dv < bd:
                p = 2.0 * alpha_c[c]
                # leading order of f near the corner: w - w_c ~ A delta^p, A from the tabulated neighbour
                uc = corner_u(c, K, Kp)
                dref = u0 - uc
                if dref != 0.0 and _nearest_corner(u0, K, Kp, radius) == c:
                    # angles measured inside this corner's quadrant of the rectangle (no branch-cut surprises)
                    lo = 0.5 * PI if c == 0 else (-PI if c == 1 else (-0.5 * PI if c == 2 else 0.0))
                    th_ref = math.atan2(dref.imag, dref.real)
                    while th_ref > lo + 0.5 * PI + 1e-12:
                        th_ref -= 2.0 * PI
                    while th_ref < lo - 1e-12:
                        th_ref += 2.0 * PI
                    A = (table_w[best] - w[corner_vtx[c]]) / np.exp(p * (math.log(abs(dref)) + 1j * th_ref))
                    lz = np.log(_sdiv(wp - w[corner_vtx[c]], A))
                    # the branch of the p-th root that points into the rectangle from this corner
                    for kb in range(-3, 4):
                        th = (lz.imag + 2.0 * PI * kb) / p
                        if lo - 1e-12 <= th <= lo + 0.5 * PI + 1e-12:
                            c0 = c
                            d0 = _project_delta(c, math.exp(lz.real / p) * (math.cos(th) + 1j * math.sin(th)), K, Kp)
                            bd = dv
                            break
        c1, d1, r1 = inverse_one(wp, c0, d0, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, corner_vtx,
                                 alpha_c, tol, radius)
        cs[i] = c1
        ds[i] = d1
        rs[i] = r1
        _ = nv
    return cs, ds, rs


# ------------------------------------------------------------------------------------- fused teacher -> learner
_SQ = np.array([0.0 + 0.0j, 1.0 + 0.0j, 1.0 + 1.0j, 0.0 + 1.0j])
_RT = np.array([1.0 + 0.0j, 1.0j, -1.0 + 0.0j, -1.0j])


@njit(cache=True, error_model="numpy")
def transfer_many(wps, T, Lm, near: float) -> np.ndarray:
    """u_T -> u_L for many points in one compiled call (the hot path of the transfer policy).

    ``T`` and ``Lm`` are the two maps' parameter tuples (see ``RectangleMap._ktuple``). Teacher points outside the
    teacher polygon give NaN (the caller checks and reports). Near a corner the unit-square offset is handed over
    exactly: user corner + offset, never rounded to a float next to 1.
    """
    (m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, ic, alpha_c, tol, radius, r, tu, tw, verts, ptol) = T
    (m2, kp2, K2, Kp2, z2, beta2, sig2, qx2, qw2, lx2, lw2, w2, cc2, ic2, ac2, tol2, rad2, r2, tu2, tw2, verts2,
     ptol2) = Lm
    n = wps.shape[0]
    out = np.empty(n, dtype=np.complex128)
    inside = points_in_polygon(wps, verts, ptol)
    for i in range(n):
        if not inside[i]:
            out[i] = complex(np.nan, np.nan)
            continue
        cs, ds, _ = inverse_many(wps[i:i + 1], tu, tw, m, kp, K, Kp, z, beta, sig, qx, qw, lx, lw, w, cc, ic,
                                 alpha_c, tol, radius)
        c = cs[0]
        d = ds[0]
        if c >= 0:
            uc = (c + r) % 4
            dprime = d.imag / Kp - 1j * d.real / (2.0 * K)
            dd = _RT[r] * dprime  # user unit-square offset from user corner uc
        else:
            pprime = d.imag / Kp + 1j * (K - d.real) / (2.0 * K)
            p = _SQ[r] + _RT[r] * pprime
            # is it close to a user corner after all? then hand over as corner + offset
            uc = -1
            best = near
            for k in range(4):
                dk = abs(p - _SQ[k])
                if dk < best:
                    best = dk
                    uc = k
            dd = p - _SQ[uc] if uc >= 0 else p
        # learner side
        if uc >= 0:
            dpl = dd / _RT[r2]
            cl = (uc - r2) % 4
            dl = -2.0 * K2 * dpl.imag + 1j * Kp2 * dpl.real
        else:
            pp = (dd - _SQ[r2]) / _RT[r2]
            pp = min(max(pp.real, 0.0), 1.0) + 1j * min(max(pp.imag, 0.0), 1.0)
            cl = -1
            dl = K2 - 2.0 * K2 * pp.imag + 1j * Kp2 * pp.real
        out[i] = forward_one(cl, dl, m2, kp2, K2, Kp2, z2, beta2, sig2, qx2, qw2, lx2, lw2, w2, cc2, ic2)[0]
    return out
