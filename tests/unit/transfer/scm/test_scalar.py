"""transfer/scm/_scalar.py: the constants and the one scalar helper every compiled kernel of the SC map shares."""

from __future__ import annotations

import cmath
import math

import numpy as np

from transfer.scm._scalar import EPS, LOG2, PI, _sdiv


def test_the_constants_are_the_floats_they_name() -> None:
    assert math.pi == PI and math.log(2.0) == LOG2 and np.finfo(float).eps == EPS


def test_sdiv_divides_and_gives_nan_instead_of_raising_on_zero() -> None:
    assert _sdiv(3 + 4j, 1 - 2j) == (3 + 4j) / (1 - 2j)
    assert _sdiv(1.0 + 0j, 2j) == -0.5j
    for a in (1 + 1j, 0j):  # numba raises ZeroDivisionError on a complex division by zero; this does not
        q = _sdiv(a, 0j)
        assert cmath.isnan(q) and math.isnan(q.real) and math.isnan(q.imag)
