"""The pieces the transfer step stands on: pairing (the teacher-equivalent command), refinement of raw pairs into
refined ones, the learner's limits, the mapping regions and their mappers, and the pair store's persistence."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.boxes import LB, TB, affine_store
from transfer.domain import Bounds
from transfer.limits import calibration_commands
from transfer.pairs import teacher_equivalent
from transfer.policy import make_policy
from transfer.store import PairStore
from transfer.teacher.unicycle import step


# ------------------------------------------------------------------------------------------------ pairing
@settings(max_examples=200, deadline=None)
@given(
    st.floats(-50, 50), st.floats(-50, 50), st.floats(-10, 10), st.floats(-2, 2), st.floats(-3, 3),
    st.sampled_from([0.02, 0.1, 0.5]),
)
def test_pairing_recovers_the_exact_teacher_command(x, y, th, v, w, dt) -> None:
    x0 = np.array([x, y, th])
    x1 = step(x0, [v, w], dt)
    x1[2] = x1[2] + 2 * math.pi * round(x1[2])  # headings may come wrapped differently: still the same motion
    u = teacher_equivalent(x0, x1, dt)
    assert u[0] == pytest.approx(v, abs=1e-9) and u[1] == pytest.approx(w, abs=1e-9)


def test_pairing_least_squares_and_bad_input() -> None:
    # a purely sideways move: no unicycle command reproduces it, the best is v = 0
    u = teacher_equivalent([0, 0, 0], [0, 0.1, 0], 0.1)
    assert u[0] == pytest.approx(0.0) and u[1] == pytest.approx(0.0)
    with pytest.raises(ValueError):
        teacher_equivalent([0, 0, 0], [np.nan, 0, 0], 0.1)
    with pytest.raises(ValueError):
        teacher_equivalent([0, 0, 0], [0, 0, 0], 0.0)


# --------------------------------------------------------------------------------------------- refinement
def test_refinement_needs_k_min_members_and_averages_them() -> None:
    s = PairStore(LB, TB, k_min=5)
    uL = LB.denormalise([0.55, 0.55])
    rng = np.random.default_rng(0)
    uts = [np.array([0.2, 0.1]) + 0.01 * rng.standard_normal(2) for _ in range(5)]
    for k, ut in enumerate(uts[:4]):
        r = s.add(ut, uL + 1e-4 * k)
        assert not r.refined_changed
    assert s.refined() == []
    r = s.add(uts[4], uL)
    assert r.refined_changed
    (p,) = s.refined()
    np.testing.assert_allclose(p.u_T, np.mean(uts, axis=0), atol=1e-12)
    np.testing.assert_allclose(p.u_L, uL + 1e-4 * np.mean([0, 1, 2, 3, 0]), atol=1e-12)
    assert p.count == 5 and p.version == 1 and p.id == s.cell_of(uL)[0] * 11 + s.cell_of(uL)[1]


def test_refined_pair_keeps_id_and_changes_version_only_when_it_moves() -> None:
    s = PairStore(LB, TB, k_min=2, move_tol=1e-3)
    uL = LB.denormalise([0.15, 0.85])
    for _ in range(2):
        s.add([0.2, 0.1], uL)
    (p,) = s.refined()
    for _ in range(50):  # more of the same: no movement, same version
        s.add([0.2, 0.1], uL)
    (q,) = s.refined()
    assert (q.id, q.version) == (p.id, p.version)
    for _ in range(50):  # a different teacher response: the mean moves
        s.add([0.3, 0.2], uL)
    (q,) = s.refined()
    assert q.id == p.id and q.version > p.version


def test_memory_is_bounded_whatever_the_number_of_pairs() -> None:
    s = PairStore(LB, TB)
    size0 = len(s.to_bytes())
    rng = np.random.default_rng(1)
    for _ in range(3000):
        uL = LB.denormalise(rng.random(2))
        s.add(TB.denormalise(rng.random(2)), uL)
    assert s.raw_count == 3000
    assert len(s.to_bytes()) <= size0 * 1.5  # the state is the grid, not the history


# ------------------------------------------------------------------------------------------ learner limits
def test_calibration_on_a_per_axis_scaled_learner_yields_exactly_the_scaled_box() -> None:
    learner = Bounds((0.0, 1.0), (-math.pi / 8, math.pi / 8))
    teacher = Bounds((0.0, 3.0), (-math.pi / 3, math.pi / 3))
    g = np.array([1.2, 1.6])
    s = PairStore(learner, teacher, k_min=1)
    for uL in calibration_commands(learner, 5):
        x0 = np.array([0.0, 0.0, 0.3])
        x1 = step(x0, g * uL, 1.0)  # the learner moves like the teacher under the scaled command
        s.add(teacher_equivalent(x0, x1, 1.0), uL)
    box = s.limits.box
    assert box.v == pytest.approx((0.0, 1.2), abs=1e-12)
    assert box.w == pytest.approx((-1.6 * math.pi / 8, 1.6 * math.pi / 8), abs=1e-12)
    hull = s.limits.hull
    assert hull.shape[0] >= 4
    assert s.limits.contains([0.6, 0.0]) and not s.limits.contains([1.5, 0.0])
    assert s.limits.contains([0.6, 0.0], use_hull=True) and not s.limits.contains([0.6, 0.7], use_hull=True)


def test_online_rules_follow_eq_learn_capability() -> None:
    s = PairStore(LB, TB, k_min=5)
    assert s.limits.box == TB  # before any pair: the teacher's own range
    # an outlier inside the learner domain: proportional shrink on both sides of each axis it is extreme on
    l_n = np.array([0.5, 0.6])
    t_n = np.array([0.2, 0.45])
    s.add(TB.denormalise(t_n), LB.denormalise(l_n))
    lim = s.limits
    assert lim.hi[0] == pytest.approx(t_n[0] / l_n[0])
    assert lim.hi[1] == pytest.approx(t_n[1] / l_n[1])
    assert lim.lo[0] == 0.0  # 1 - 0.8 / 0.5 < 0: the teacher's own range is the outer limit
    low = PairStore(LB, TB, k_min=5)  # the mirrored rule for the lower side
    low.add(TB.denormalise([0.7, 0.5]), LB.denormalise([0.4, 0.5]))
    assert low.limits.lo[0] == pytest.approx(1 - (1 - 0.7) / (1 - 0.4))
    # a later outlier that is further out replaces the estimate; one that is not an outlier does nothing
    before = lim.hi.copy()
    s.add(TB.denormalise([0.1, 0.1]), LB.denormalise([0.3, 0.55]))
    assert lim.hi[0] == before[0] and lim.hi[1] == before[1]
    s.add(TB.denormalise([0.35, 0.5]), LB.denormalise([0.7, 0.55]))
    assert lim.hi[0] == pytest.approx(0.35 / 0.7)
    # a pair on the learner's boundary marks the bound itself, and later outliers inside no longer move it
    s.add(TB.denormalise([0.45, 0.5]), LB.denormalise([1.0, 0.55]))
    assert lim.hi[0] == pytest.approx(0.45)
    s.add(TB.denormalise([0.47, 0.5]), LB.denormalise([1.0, 0.52]))
    assert lim.hi[0] == pytest.approx(0.46)  # mean of the boundary pairs
    s.add(TB.denormalise([0.2, 0.5]), LB.denormalise([0.9, 0.5]))
    assert lim.hi[0] == pytest.approx(0.46)
    assert s.limits.box.v[1] == pytest.approx(TB.denormalise([0.46, 0])[0])


# ------------------------------------------------------------------------------------------------ mappers
@pytest.mark.parametrize("mapper", ["scm", "barycentric", "affine"])
def test_mappers_reproduce_a_per_axis_affine_learner_inside_the_hull(mapper: str) -> None:
    s, a, b = affine_store()
    p = make_policy(s, mapper, seed=0, choice=False)  # each mapper alone
    rng = np.random.default_rng(5)
    for _ in range(60):
        uL = LB.denormalise(0.02 + 0.96 * rng.random(2))
        m = p.map(a * uL + b)
        assert m.method == mapper
        np.testing.assert_allclose(m.u_L, uL, atol=1e-9)
        assert len(m.region) == {"scm": 4, "barycentric": 3, "affine": 121}[mapper]


def test_scm_regions_are_cached_and_rebuilt_when_a_pair_moves() -> None:
    s, a, b = affine_store(k_min=1)
    p = make_policy(s, "scm", seed=0, choice=False)  # the SC map alone
    uT = a * LB.denormalise([0.5, 0.5]) + b
    m1 = p.map(uT)
    builds = p.mapper.builds
    p.map(uT)
    assert p.mapper.builds == builds  # cache hit
    # move one of the region's pairs: its version changes and the region is rebuilt
    pid = m1.region[0]
    cell = divmod(pid, 11)
    uL_cell = s.learner_bounds.denormalise(s.cells.pub_L[cell])
    for _ in range(200):
        s.add(s.teacher_bounds.denormalise(s.cells.pub_T[cell]) + np.array([0.01, 0.0]), uL_cell)
    m2 = p.map(uT)
    assert p.mapper.builds > builds
    assert np.all(np.isfinite(m2.u_L))


# -------------------------------------------------------------------------------------------- persistence
def test_store_round_trips_and_rejects_corruption() -> None:
    s, a, b = affine_store(k_min=2)
    s.add(a * LB.denormalise([1.0, 0.5]) + b, LB.denormalise([1.0, 0.5]))
    blob = s.to_bytes()
    t = PairStore.from_bytes(blob)
    assert t.to_bytes() == blob
    assert [(p.id, p.version, p.count) for p in t.refined()] == [(p.id, p.version, p.count) for p in s.refined()]
    assert t.limits.box == s.limits.box
    uT = a * LB.denormalise([0.4, 0.6]) + b
    np.testing.assert_allclose(make_policy(t).map(uT).u_L, make_policy(s).map(uT).u_L, atol=1e-12)
    bad = bytearray(blob)
    bad[len(bad) // 2] ^= 0x55
    for corrupt, match in [
        (bytes(bad), "CRC"),
        (blob[: len(blob) // 2], "CRC"),
        (b"garbage", "magic"),
        (b"", "magic"),
    ]:
        with pytest.raises(ValueError, match=match):
            PairStore.from_bytes(corrupt)


def test_store_rejects_an_incompatible_schema_version() -> None:
    import zlib

    import msgspec

    s = PairStore(LB, TB)
    raw = msgspec.msgpack.decode(s.to_bytes()[12:])
    raw["schema_version"] = 99
    payload = msgspec.msgpack.encode(raw)
    blob = b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload
    with pytest.raises(ValueError, match="version 99"):
        PairStore.from_bytes(blob)
    raw["schema_version"] = 2
    raw["count"] = raw["count"][:-1]
    payload = msgspec.msgpack.encode(raw)
    blob = b"SCMPAIRS" + zlib.crc32(payload).to_bytes(4, "little") + payload
    with pytest.raises(ValueError, match="count"):
        PairStore.from_bytes(blob)
