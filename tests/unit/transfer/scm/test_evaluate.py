"""transfer/scm/_evaluate.py: the compiled evaluation of the SC rectangle map (rectangle <-> strip <-> polygon,
forward, inverse, and the fused teacher -> learner transfer).

The public maps built on it (RectangleMap.to_unit_square / from_unit_square, QuadTransfer) are tested in
tests/unit/transfer/scm/test_rectmap.py (round trips next to corners, edges to sides, holomorphy); here the kernels on
a solved map's own parameters: the corners, the strip's corner images, the inverse of the forward map in the
rectangle's coordinates, and the fused transfer through one map and back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from transfer.scm import RectangleMap
from transfer.scm._evaluate import _log1p_c, corner_u, forward_many, inverse_many, rect_to_strip, transfer_many

F = RectangleMap([0, 2, 2.3 + 1.1j, -0.4 + 0.8j])


def test_corner_u_and_log1p_c() -> None:
    K, Kp = 1.5, 0.7
    assert [corner_u(c, K, Kp) for c in range(4)] == [K, K + 1j * Kp, -K + 1j * Kp, -K]
    for e in (0.3 + 0.2j, -0.5 + 0.1j, 2 - 3j):
        assert _log1p_c(e) == pytest.approx(np.log(1 + e), rel=1e-14)
    tiny = 1e-20 + 3e-20j
    assert _log1p_c(tiny) == pytest.approx(tiny, rel=1e-12)  # where log(1 + e) would round to 0


def test_the_rectangles_corners_go_to_the_strips_corners() -> None:
    m, kp, K, Kp, L = F._m, F._kp, F._K, F._Kp, F.L
    for c, want in enumerate([0.0, L, L + 1j, 1j]):
        k, s, _ = rect_to_strip(-1, corner_u(c, K, Kp), m, kp, K, Kp)  # absolute form
        assert k == -1 and s == pytest.approx(want, abs=1e-8)
        k, s, _ = rect_to_strip(c, 0j, m, kp, K, Kp)  # corner-local form: the corner itself, offset 0
        assert k == c and s == 0


def test_forward_takes_the_rectangles_corners_to_the_polygons() -> None:
    cs = np.arange(4, dtype=np.int64)
    got = forward_many(cs, np.zeros(4, dtype=np.complex128), *F._args())
    np.testing.assert_allclose(got, F._w[F._ic], atol=1e-12)


def test_inverse_undoes_forward_inside_the_rectangle() -> None:
    K, Kp = F._K, F._Kp
    rng = np.random.default_rng(5)
    u = rng.uniform(-0.95, 0.95, 30) * K + 1j * rng.uniform(0.05, 0.95, 30) * Kp
    w = forward_many(np.full(30, -1, dtype=np.int64), u, *F._args())
    tu, tw = F._ensure_table()
    tol = 1e-13 * F.scale
    cs, ds, rs = inverse_many(w, tu, tw, *F._args(), F._alpha_c, tol, F._radius)
    back = np.array([corner_u(int(c), K, Kp) + d if c >= 0 else d for c, d in zip(cs, ds)])
    assert np.all(rs <= 10 * tol)
    np.testing.assert_allclose(back, u, atol=1e-9 * K)
    # a vertex that is a corner is found exactly, as the corner with offset 0
    cs, ds, rs = inverse_many(F._w[F._ic[2:3]], tu, tw, *F._args(), F._alpha_c, tol, F._radius)
    assert (int(cs[0]), complex(ds[0]), float(rs[0])) == (2, 0j, 0.0)


def test_the_fused_transfer_through_one_map_and_back_is_the_identity_and_nan_outside() -> None:
    rng = np.random.default_rng(1)
    inside = F.from_unit_square(rng.uniform(0.02, 0.98, 20) + 1j * rng.uniform(0.02, 0.98, 20))
    pts = np.r_[inside, 5.0 + 5.0j]
    out = transfer_many(pts, F._ktuple(), F._ktuple(inverse=False), 0.2)
    np.testing.assert_allclose(out[:-1], inside, atol=1e-9 * F.scale)
    assert math.isnan(out[-1].real) and math.isnan(out[-1].imag)
