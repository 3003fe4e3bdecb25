"""Compiled complex Jacobi elliptic functions sn, cn, dn (numba, cached on disk), the rectangle -> strip step of the
SC rectangle map (docs/ARCHITECTURE.md section 9, "Complex sn, cn, dn")."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from transfer.scm._scalar import EPS, _sdiv


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
