"""transfer/scm/_parameters.py: the quadrilateral's parameter problem (its one unknown, log L) in compiled code.

RectangleMap solves it for every quadrilateral (tests/unit/transfer/scm/test_rectmap.py checks the moduli and that a
sliver is refused after a bounded search); here the residual and the damped Newton themselves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.scm import RectangleMap
from transfer.scm._parameters import quad_newton, quad_residual

QUADS = [[0, 2, 2.3 + 1.1j, -0.4 + 0.8j], [0, 5, 4.6 + 1.1j, 0.3 + 0.7j], [-1j, 0.5 - 1.2j, 0.6 + 1.3j, 1j]]


def _args(f: RectangleMap) -> tuple:
    w = f._w
    ratio = math.log(abs(w[2] - w[1]) / abs(w[1] - w[0]))  # side 1 against side 0, as rectmap.py poses it
    return f._beta, f._sig, f._qx, f._qw, f._lx, f._lw, ratio


@pytest.mark.parametrize("v", QUADS)
def test_the_residual_vanishes_at_the_maps_strip_length_and_changes_sign_there(v: list[complex]) -> None:
    f = RectangleMap(v)
    args = _args(f)
    y = math.log(f.L)
    assert abs(quad_residual(y, *args)) < 1e-11
    # a longer strip makes side 1 (across it) shorter against side 0 (along it): the residual falls through zero
    assert quad_residual(y - 0.3, *args) > 0 > quad_residual(y + 0.3, *args)


@pytest.mark.parametrize("v", QUADS)
def test_newton_converges_from_a_rough_guess(v: list[complex]) -> None:
    f = RectangleMap(v)
    args = _args(f)
    for y0 in (math.log(f.L) - 1.0, math.log(f.L) + 1.5, 0.0):
        y, F, ok = quad_newton(y0, *args, 1e-15)
        assert ok and abs(F) < 1e-12 and y == pytest.approx(math.log(f.L), abs=1e-11)


def test_newton_says_when_it_did_not_converge_and_the_residual_stays_finite() -> None:
    f = RectangleMap(QUADS[0])
    args = _args(f)
    y, F, ok = quad_newton(math.log(f.L), *args, 0.0)  # a target nothing can meet: it stalls, and says so
    assert not ok and abs(F) < 1e-11
    for y in (-60.0, 60.0, 1e4):  # far from any solution the quadrature breaks down: a finite residual
        assert np.isfinite(quad_residual(y, *args))
