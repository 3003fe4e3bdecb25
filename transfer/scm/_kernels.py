"""Compiled inner loops of the Schwarz-Christoffel rectangle map (numba, cached on disk).

Everything here is scalar arithmetic on small arrays; the Python layer (``rectmap.py``) validates input, solves
the parameter problem with these kernels and vectorises evaluation over points. The maths follows the SC Toolbox
(Driscoll; docs/ARCHITECTURE.md section 9), with two changes: corner-local evaluation (a point near a rectangle
corner is carried as the corner plus an offset, so no digits are lost to cancellation) and our own, simpler
parametrisation of the strip prevertices (see ``rectmap.py``).

Notation: strip S = {0 <= Im s <= 1}; prevertices ``z[j]`` on its edges (``sig[j] = +1`` bottom, ``-1`` top) with
turning exponents ``beta[j]`` (interior angle / pi - 1). The strip map's derivative, up to the constant ``c``, is
``F'(s) = prod_j (-i sinh(sig_j pi/2 (s - z_j)))^beta_j``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

PI = math.pi
LOG2 = math.log(2.0)
EPS = 2.220446049250313e-16


# ------------------------------------------------------------------------------------------------ polygon checks
@njit(cache=True, error_model="numpy")
def _orient(a: complex, b: complex, c: complex) -> float:
    return (b - a).real * (c - a).imag - (b - a).imag * (c - a).real


@njit(cache=True, error_model="numpy")
def _on_seg(a: complex, b: complex, c: complex, tol: float) -> bool:
    return (min(a.real, b.real) - tol <= c.real <= max(a.real, b.real) + tol
            and min(a.imag, b.imag) - tol <= c.imag <= max(a.imag, b.imag) + tol)


@njit(cache=True, error_model="numpy")
def segments_cross(p1: complex, p2: complex, q1: complex, q2: complex, tol: float) -> bool:
    """Do the closed segments p1p2 and q1q2 touch (including collinear overlap)?"""
    d1, d2 = _orient(q1, q2, p1), _orient(q1, q2, p2)
    d3, d4 = _orient(p1, p2, q1), _orient(p1, p2, q2)
    scale = tol * max(abs(p2 - p1), abs(q2 - q1), 1e-300)
    if ((d1 > scale and d2 < -scale) or (d1 < -scale and d2 > scale)) and (
        (d3 > scale and d4 < -scale) or (d3 < -scale and d4 > scale)
    ):
        return True
    return ((abs(d1) <= scale and _on_seg(q1, q2, p1, tol)) or (abs(d2) <= scale and _on_seg(q1, q2, p2, tol))
            or (abs(d3) <= scale and _on_seg(p1, p2, q1, tol)) or (abs(d4) <= scale and _on_seg(p1, p2, q2, tol)))


@njit(cache=True, error_model="numpy")
def polygon_defect(w: np.ndarray) -> tuple[int, int, int]:
    """What is wrong with polygon ``w`` (complex vertices), as ``(code, i, j)``: 0 nothing; 1 vertex i not finite;
    2 vertices i and j coincide; 3 edge i-(i+1) meets edge j-(j+1); 4 clockwise; 5 zero area; 6 vertex i a spike
    (a zero or full interior angle). ``transfer.scm.geometry.check_polygon`` words them."""
    n = w.shape[0]
    for k in range(n):
        if not (math.isfinite(w[k].real) and math.isfinite(w[k].imag)):
            return 1, k, 0
    diam = 0.0
    for i in range(n):
        for j in range(n):
            diam = max(diam, abs(w[i] - w[j]))
    tol = 1e-12 * max(diam, 1e-300)
    for i in range(n):
        for j in range(i + 1, n):
            if abs(w[i] - w[j]) <= tol:
                return 2, i, j
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # adjacent edges share a vertex
            if segments_cross(w[i], w[(i + 1) % n], w[j], w[(j + 1) % n], 1e-12):
                return 3, i, j
    area2 = 0.0
    for k in range(n):
        a, b = w[k], w[(k + 1) % n]
        area2 += a.real * b.imag - b.real * a.imag
    if area2 < 0:
        return 4, 0, 0
    if area2 <= 1e-14 * diam * diam:
        return 5, 0, 0
    for k in range(n):
        turn = (w[(k + 1) % n] - w[k]) / (w[k] - w[k - 1])
        alpha = 1.0 - math.atan2(turn.imag, turn.real) / PI
        if alpha < 1e-9 or alpha > 2.0 - 1e-9:
            return 6, k, 0
    return 0, 0, 0


# ----------------------------------------------------------------------------------------------- quadrature rules
@njit(cache=True, error_model="numpy")
def gauss_jacobi(nq: int, b: float) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Jacobi nodes/weights on [-1, 1] for the weight (1 + x)^b (Golub-Welsch); b = 0 gives Legendre."""
    a = 0.0
    J = np.zeros((nq, nq))
    for n in range(nq):
        s = 2.0 * n + a + b
        if n == 0:
            J[0, 0] = (b - a) / (a + b + 2.0)
        else:
            J[n, n] = (b * b - a * a) / (s * (s + 2.0))
        if n >= 1:
            m = float(n)
            s1 = 2.0 * m + a + b
            off = 4.0 * m * (m + a) * (m + b) * (m + a + b) / (s1 * s1 * (s1 + 1.0) * (s1 - 1.0))
            J[n, n - 1] = math.sqrt(off)
            J[n - 1, n] = J[n, n - 1]
    lam, V = np.linalg.eigh(J)
    mu0 = 2.0 ** (a + b + 1.0) * math.exp(math.lgamma(a + 1.0) + math.lgamma(b + 1.0) - math.lgamma(a + b + 2.0))
    w = mu0 * V[0, :] ** 2
    return lam, w


@njit(cache=True, error_model="numpy")
def jacobi_table(beta: np.ndarray, nq: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Jacobi rule per prevertex (singularity at the left end, power beta_j) and one Legendre rule."""
    n = beta.shape[0]
    qx = np.empty((n, nq))
    qw = np.empty((n, nq))
    for j in range(n):
        x, w = gauss_jacobi(nq, beta[j])
        qx[j, :] = x
        qw[j, :] = w
    lx, lw = gauss_jacobi(nq, 0.0)
    return qx, qw, lx, lw


# ------------------------------------------------------------------------------------------- strip integrand
@njit(cache=True, error_model="numpy")
def _sdiv(a: complex, b: complex) -> complex:
    """a / b, NaN (not an exception: numba raises on complex division by zero) when b == 0."""
    if b == 0.0:
        return complex(np.nan, np.nan)
    return a / b


@njit(cache=True, error_model="numpy")
def _logfac(t: complex) -> complex:
    """log(-i sinh t), continuous for t = sig pi/2 (s - z) with s in the closed strip; asymptotic for |Re t| > 40."""
    if t.real > 40.0:
        return t - 0.5j * PI - LOG2
    if t.real < -40.0:
        return -t + 0.5j * PI - LOG2
    return np.log(-1j * np.sinh(t))


@njit(cache=True, error_model="numpy")
def log_fprime(s: complex, z: np.ndarray, beta: np.ndarray, sig: np.ndarray, k: int, dk: complex) -> complex:
    """log F'(s). If ``k >= 0`` the factor of prevertex k is evaluated from the exact offset ``dk = s - z_k`` and
    divided by |dk|^beta_k (the Gauss-Jacobi weight carries that part)."""
    acc = 0.0 + 0.0j
    for j in range(z.shape[0]):
        if j == k:
            acc += beta[j] * (_logfac(sig[j] * 0.5 * PI * dk) - math.log(abs(dk)))
        else:
            acc += beta[j] * _logfac(sig[j] * 0.5 * PI * (s - z[j]))
    return acc


@njit(cache=True, error_model="numpy")
def log_fprime_at(z: np.ndarray, beta: np.ndarray, sig: np.ndarray, k: int, dk: complex) -> complex:
    """log F'(z_k + dk) without normalisation, the factor of k taken from the exact offset dk."""
    acc = 0.0 + 0.0j
    s = z[k] + dk
    for j in range(z.shape[0]):
        if j == k:
            acc += beta[j] * _logfac(sig[j] * 0.5 * PI * dk)
        else:
            acc += beta[j] * _logfac(sig[j] * 0.5 * PI * (s - z[j]))
    return acc


@njit(cache=True, error_model="numpy")
def _min_dist(p: complex, z: np.ndarray, skip: int) -> float:
    d = np.inf
    for j in range(z.shape[0]):
        if j != skip:
            dj = abs(z[j] - p)
            if dj < d:
                d = dj
    return d


@njit(cache=True, error_model="numpy")
def _legendre(za: complex, zb: complex, z, beta, sig, lx, lw) -> complex:
    h = 0.5 * (zb - za)
    mid = 0.5 * (za + zb)
    acc = 0.0 + 0.0j
    for q in range(lx.shape[0]):
        acc += lw[q] * np.exp(log_fprime(mid + h * lx[q], z, beta, sig, -1, 0j))
    return h * acc


@njit(cache=True, error_model="numpy")
def quad_regular(za: complex, zb: complex, z, beta, sig, lx, lw) -> complex:
    """Integral of F' from za to zb along the segment, no singular end: compound Legendre, pieces no longer than
    the distance of their left end to the nearest prevertex (the toolbox's 1/2 rule, made stricter)."""
    acc = 0.0 + 0.0j
    zl = za
    for _ in range(400):
        rest = abs(zb - zl)
        if rest == 0.0:
            break
        frac = min(1.0, _min_dist(zl, z, -1) / rest)
        zr = zb if frac >= 1.0 else zl + frac * (zb - zl)
        acc += _legendre(zl, zr, z, beta, sig, lx, lw)
        zl = zr
        if frac >= 1.0:
            break
    return acc


@njit(cache=True, error_model="numpy")
def quad_from(k: int, D: complex, z, beta, sig, qx, qw, lx, lw) -> complex:
    """Integral of F' from prevertex k to z_k + D: a Gauss-Jacobi piece at the singular end (its singular factor
    computed from the exact offsets), then compound Legendre."""
    if D == 0.0:
        return 0.0 + 0.0j
    dmin = _min_dist(z[k], z, k)
    frac = min(1.0, dmin / abs(D))
    D1 = frac * D
    h = 0.5 * D1
    scale = h * abs(h) ** beta[k]
    acc = 0.0 + 0.0j
    for q in range(qx.shape[1]):
        d = h * (qx[k, q] + 1.0)
        acc += qw[k, q] * np.exp(log_fprime(z[k] + d, z, beta, sig, k, d))
    acc *= scale
    if frac < 1.0:
        acc += quad_regular(z[k] + D1, z[k] + D, z, beta, sig, lx, lw)
    return acc


@njit(cache=True, error_model="numpy")
def side_integrals(z, beta, sig, qx, qw, lx, lw, count: int) -> np.ndarray:
    """Integrals of F' between consecutive prevertices j -> j+1 for j < count (along an edge through the midpoint,
    or across the strip's middle line when they sit on different edges)."""
    n = z.shape[0]
    out = np.empty(count, dtype=np.complex128)
    for j in range(count):
        a = z[j]
        b = z[(j + 1) % n]
        if sig[j] == sig[(j + 1) % n]:
            mid = 0.5 * (a + b)
            out[j] = quad_from(j, mid - a, z, beta, sig, qx, qw, lx, lw) - quad_from(
                (j + 1) % n, mid - b, z, beta, sig, qx, qw, lx, lw
            )
        else:
            ma = a.real + 0.5j
            mb = b.real + 0.5j
            out[j] = (
                quad_from(j, ma - a, z, beta, sig, qx, qw, lx, lw)
                + quad_regular(ma, mb, z, beta, sig, lx, lw)
                - quad_from((j + 1) % n, mb - b, z, beta, sig, qx, qw, lx, lw)
            )
    return out


@njit(cache=True, error_model="numpy")
def quad_residual(y: float, beta, sig, qx, qw, lx, lw, ratio: float) -> float:
    """The quadrilateral's parameter residual at ``y = log L``: log|I_1| - log|I_0| - ratio for the strip
    prevertices 0, L, L + i, i (1e3 where the quadrature breaks down: far from the solution, said finitely)."""
    L = math.exp(min(y, 700.0 / (2.0 * PI)))
    z = np.empty(4, dtype=np.complex128)
    z[0], z[1], z[2], z[3] = 0.0, L, L + 1j, 1j
    ints = side_integrals(z, beta, sig, qx, qw, lx, lw, 2)
    F = math.log(abs(ints[1])) - math.log(abs(ints[0])) - ratio
    return F if math.isfinite(F) else 1e3


@njit(cache=True, error_model="numpy")
def quad_newton(y0: float, beta, sig, qx, qw, lx, lw, ratio: float, target: float) -> tuple[float, float, bool]:
    """Damped Newton on the quadrilateral's one unknown ``log L`` (forward-difference slope, steps of at most 2,
    halved until the residual drops): ``(y, F, converged)`` with ``converged`` when ``|F| < target``, or
    ``|F| < 1e3 target`` once Newton stalls. The caller falls back to a bracketed search otherwise."""
    y = y0
    F = quad_residual(y, beta, sig, qx, qw, lx, lw, ratio)
    for _ in range(60):
        if not math.isfinite(F):
            break
        if abs(F) < target:
            return y, F, True
        h = 1e-6
        dF = (quad_residual(y + h, beta, sig, qx, qw, lx, lw, ratio) - F) / h
        step = -F / dF if dF != 0.0 and math.isfinite(dF) else 0.5
        step = max(-2.0, min(2.0, step))
        lam = 1.0
        improved = False
        yn, Fn = y, F
        for _h in range(30):
            yn = y + lam * step
            Fn = quad_residual(yn, beta, sig, qx, qw, lx, lw, ratio)
            if math.isfinite(Fn) and abs(Fn) < abs(F):
                improved = True
                break
            lam *= 0.5
        if not improved:
            break
        y, F = yn, Fn
    return y, F, math.isfinite(F) and abs(F) < 1e3 * target


# ----------------------------------------------------------------------------------------- complex sn, cn, dn
@njit(cache=True, error_model="numpy")
def ellipjc(u: complex, m: float, kp: float, Kp: float) -> tuple[complex, complex, complex]:
    """Jacobi sn, cn, dn of complex u for parameter m (kp = sqrt(1 - m) given accurately, Kp = K(1 - m)).

    Descending Landen transformation with reflection of the upper half of the period rectangle (SC Toolbox
    ``ellipjc``): |Im u| stays <= Kp / 2, so the trigonometric base case neither overflows nor loses digits.
    """
    lower = u.imag < 0.0
    if lower:  # sn(conj u) = conj(sn u) for real m: work in the upper half
        u = u.conjugate()
    high = u.imag > 0.5 * Kp
    if high:
        u = 1j * Kp - u
    kappas = np.empty(32)
    nk = 0
    mm = m
    first = True
    while mm >= 4.0 * EPS and nk < 32:
        if mm > 1e-3:
            r = kp if first else math.sqrt(1.0 - mm)
            kappa = (1.0 - r) / (1.0 + r)
        else:
            x = 0.25 * mm
            kappa = x * (1.0 + x * (2.0 + x * (5.0 + x * (14.0 + x * (42.0 + x * 132.0)))))
        first = False
        kappas[nk] = kappa
        nk += 1
        u = u / (1.0 + kappa)
        mm = kappa * kappa
    sinu = np.sin(u)
    cosu = np.cos(u)
    t = 0.25 * mm * (sinu * cosu - u)
    sn = sinu + t * cosu
    cn = cosu - t * sinu
    dn = 1.0 + 0.25 * mm * (cosu * cosu - sinu * sinu - 1.0)
    for i in range(nk - 1, -1, -1):
        kap = kappas[i]
        den = 1.0 + kap * sn * sn
        sn, cn, dn = _sdiv((1.0 + kap) * sn, den), _sdiv(cn * dn, den), _sdiv(1.0 - kap * sn * sn, den)
    if high:
        k = math.sqrt(m)
        sn, cn, dn = _sdiv(-1.0, k * sn), _sdiv(1j * dn, k * sn), _sdiv(1j * cn, sn)
    if lower:
        return sn.conjugate(), cn.conjugate(), dn.conjugate()
    return sn, cn, dn


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


@njit(cache=True, error_model="numpy")
def points_in_polygon(p: np.ndarray, w: np.ndarray, tol: float) -> np.ndarray:
    """True where p is inside the closed polygon w (points within tol of an edge count as inside)."""
    n = w.shape[0]
    out = np.zeros(p.shape[0], dtype=np.bool_)
    for i in range(p.shape[0]):
        x = p[i].real
        y = p[i].imag
        inside = False
        on_edge = False
        for j in range(n):
            a = w[j]
            b = w[(j + 1) % n]
            ab = b - a
            L2 = ab.real * ab.real + ab.imag * ab.imag
            t = ((p[i] - a).real * ab.real + (p[i] - a).imag * ab.imag) / L2
            t = min(max(t, 0.0), 1.0)
            if abs(p[i] - (a + t * ab)) <= tol:
                on_edge = True
                break
            if (a.imag > y) != (b.imag > y):
                xc = a.real + (y - a.imag) * ab.real / ab.imag
                if x < xc:
                    inside = not inside
        out[i] = inside or on_edge
    return out


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
