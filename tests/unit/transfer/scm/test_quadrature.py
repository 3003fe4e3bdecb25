"""transfer/scm/_quadrature.py: the Gauss-Jacobi tables and the integrals of the SC strip map's derivative F'.

The whole map's accuracy (moduli with known answers, SC Toolbox goldens) is tested through RectangleMap in
tests/unit/transfer/scm/test_rectmap.py; here the kernels' own promises: the rules are Gauss-Jacobi's, an integrand
with no singular factor (every beta 0, F' = 1) integrates exactly, the integrals are path independent and their
derivative is F', and a solved map's side integrals reproduce its polygon's sides."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special

from transfer.scm import RectangleMap
from transfer.scm._quadrature import (
    _logfac,
    gauss_jacobi,
    jacobi_table,
    log_fprime,
    log_fprime_at,
    quad_from,
    quad_regular,
    side_integrals,
)


@pytest.mark.parametrize("b", [0.0, -0.5, -0.75, 0.5, 1.3])
def test_gauss_jacobi_is_the_rule_of_the_weight_one_plus_x_to_the_b(b: float) -> None:
    x, w = gauss_jacobi(10, b)
    xs, ws = scipy.special.roots_jacobi(10, 0.0, b)  # weight (1 - x)^0 (1 + x)^b
    order = np.argsort(x)
    np.testing.assert_allclose(x[order], xs, atol=1e-13)
    np.testing.assert_allclose(w[order], ws, rtol=1e-11)
    assert w.sum() == pytest.approx(2 ** (b + 1) / (b + 1), rel=1e-13)


def test_jacobi_table_holds_one_rule_per_prevertex_and_a_legendre_rule() -> None:
    beta = np.array([-0.5, -0.25, 0.5])
    qx, qw, lx, lw = jacobi_table(beta, 8)
    assert qx.shape == qw.shape == (3, 8) and lx.shape == lw.shape == (8,)
    for j, b in enumerate(beta):
        x, w = gauss_jacobi(8, b)
        np.testing.assert_array_equal(qx[j], x)
        np.testing.assert_array_equal(qw[j], w)
    xl, wl = np.polynomial.legendre.leggauss(8)
    np.testing.assert_allclose(np.sort(lx), xl, atol=1e-14)
    np.testing.assert_allclose(lw[np.argsort(lx)], wl, atol=1e-14)


def _strip(L: float, beta: np.ndarray) -> tuple:
    z = np.array([0.0, L, L + 1j, 1j])
    sig = np.array([1.0, 1.0, -1.0, -1.0])
    return (z, beta, sig, *jacobi_table(beta, 12))


def test_with_no_singular_factor_the_integrals_are_the_displacements() -> None:
    z, beta, sig, qx, qw, lx, lw = _strip(1.5, np.zeros(4))
    assert quad_regular(0.2 + 0.1j, 1.3 + 0.8j, z, beta, sig, lx, lw) == pytest.approx(1.1 + 0.7j, abs=1e-14)
    assert quad_from(1, -0.4 + 0.6j, z, beta, sig, qx, qw, lx, lw) == pytest.approx(-0.4 + 0.6j, abs=1e-14)
    assert quad_from(2, 0j, z, beta, sig, qx, qw, lx, lw) == 0
    np.testing.assert_allclose(side_integrals(z, beta, sig, qx, qw, lx, lw, 4), np.diff(np.r_[z, z[0]]), atol=1e-14)


def test_integrals_are_path_independent_and_their_derivative_is_f_prime() -> None:
    z, beta, sig, qx, qw, lx, lw = _strip(0.8, np.array([-0.5, -0.3, -0.6, -0.6]))
    k, D = 0, 0.5 + 0.4j
    whole = quad_from(k, D, z, beta, sig, qx, qw, lx, lw)
    for f in (0.1, 0.5, 0.9):
        part = quad_from(k, f * D, z, beta, sig, qx, qw, lx, lw) + quad_regular(
            z[k] + f * D, z[k] + D, z, beta, sig, lx, lw)
        assert part == pytest.approx(whole, rel=1e-12)
    h = 1e-6
    slope = (quad_from(k, D + h, z, beta, sig, qx, qw, lx, lw) - quad_from(k, D - h, z, beta, sig, qx, qw, lx, lw)) / (
        2 * h)
    assert slope == pytest.approx(np.exp(log_fprime_at(z, beta, sig, k, D)), rel=1e-7)
    # the normalised and unnormalised forms of log F' differ by the Gauss-Jacobi weight's part, beta_k log|dk|
    assert log_fprime(z[k] + D, z, beta, sig, k, D) + beta[k] * math.log(abs(D)) == pytest.approx(
        log_fprime_at(z, beta, sig, k, D), rel=1e-14)
    assert log_fprime(z[k] + D, z, beta, sig, -1, 0j) == pytest.approx(log_fprime_at(z, beta, sig, k, D), rel=1e-12)


def test_logfac_switches_to_its_asymptote_without_a_jump() -> None:
    for t in (39.999 + 0.3j, 40.001 + 0.3j, -39.999 - 0.2j, -40.001 - 0.2j):
        assert _logfac(t) == pytest.approx(np.log(-1j * np.sinh(t)), rel=1e-14)
    assert np.isfinite(_logfac(800.0 + 0.1j))  # where sinh itself overflows


@pytest.mark.parametrize("v", [[0, 2, 2.3 + 1.1j, -0.4 + 0.8j], [0, 5, 4.6 + 1.1j, 0.3 + 0.7j]])
def test_a_solved_maps_side_integrals_reproduce_its_polygons_sides(v: list[complex]) -> None:
    f = RectangleMap(v)
    ints = side_integrals(f._z, f._beta, f._sig, f._qx, f._qw, f._lx, f._lw, 4)
    sides = np.diff(np.r_[f._w, f._w[0]])
    np.testing.assert_allclose(f._c * ints, sides, atol=1e-10 * np.abs(sides).max())
