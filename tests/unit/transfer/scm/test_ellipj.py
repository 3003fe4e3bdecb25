"""transfer/scm/_ellipj.py: complex Jacobi sn, cn, dn (the rectangle -> strip step of the SC rectangle map).

Their accuracy against mpmath on the period rectangle's upper half, the identities sn^2 + cn^2 = 1 and
dn^2 + m sn^2 = 1, the real axis against scipy and the imaginary shift are tested in
tests/unit/transfer/scm/test_rectmap.py; here the special values, the symmetries (the lower half-plane goes through
the conjugation branch) and the trigonometric limit m -> 0."""

from __future__ import annotations

import cmath
import math

import pytest
import scipy.special

from transfer.scm._ellipj import ellipjc


def _params(m: float) -> tuple[float, float, float]:
    return math.sqrt(1.0 - m), float(scipy.special.ellipk(m)), float(scipy.special.ellipkm1(m))


@pytest.mark.parametrize("m", [1e-8, 0.2, 0.7, 0.999])
def test_special_values_at_zero_and_the_quarter_period(m: float) -> None:
    kp, K, Kp = _params(m)
    assert ellipjc(0j, m, kp, Kp) == (0, 1, 1)
    sn, cn, dn = ellipjc(complex(K, 0.0), m, kp, Kp)
    assert abs(sn - 1) < 1e-13 and abs(cn) < 1e-7 and abs(dn - kp) < 1e-12


@pytest.mark.parametrize("m", [1e-8, 0.2, 0.7, 0.999])
def test_conjugate_and_odd_even_symmetries(m: float) -> None:
    kp, K, Kp = _params(m)
    for u in (0.3 * K + 0.2j * Kp, -0.8 * K + 0.45j * Kp, 0.5 * K + 0.9j * Kp):
        sn, cn, dn = ellipjc(u, m, kp, Kp)
        snc, cnc, dnc = ellipjc(u.conjugate(), m, kp, Kp)  # the lower half-plane: conjugated
        assert (snc, cnc, dnc) == pytest.approx((sn.conjugate(), cn.conjugate(), dn.conjugate()), rel=1e-12)
        sn_, cn_, dn_ = ellipjc(-u, m, kp, Kp)  # sn odd, cn and dn even
        assert (sn_, cn_, dn_) == pytest.approx((-sn, cn, dn), rel=1e-12)


def test_parameter_zero_is_the_trigonometric_case() -> None:
    for u in (0.3 + 0.2j, -1.2 + 0.7j, 2.0 - 0.4j):
        sn, cn, dn = ellipjc(u, 0.0, 1.0, math.inf)
        assert sn == pytest.approx(cmath.sin(u), rel=1e-15) and cn == pytest.approx(cmath.cos(u), rel=1e-15)
        assert dn == 1.0
