"""Compiled parameter solve of the quadrilateral's rectangle map (numba, cached on disk): its one unknown, the strip
length L, found by damped Newton on log L (docs/ARCHITECTURE.md section 9, "Parameter problem"; ``rectmap.py``
falls back to a bracketed search and solves N > 4 with scipy)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from transfer.scm._quadrature import side_integrals
from transfer.scm._scalar import PI


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
