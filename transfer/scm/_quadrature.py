"""Compiled quadrature of the SC strip map (numba, cached on disk): Gauss-Jacobi tables and integrals of F'.

Notation: strip S = {0 <= Im s <= 1}; prevertices ``z[j]`` on its edges (``sig[j] = +1`` bottom, ``-1`` top) with
turning exponents ``beta[j]`` (interior angle / pi - 1). The strip map's derivative, up to the constant ``c``, is
``F'(s) = prod_j (-i sinh(sig_j pi/2 (s - z_j)))^beta_j``. Compound Gauss-Jacobi rules carry the singular power at
a prevertex as their weight (docs/ARCHITECTURE.md section 9, "Quadrature").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from transfer.scm._scalar import LOG2, PI


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
