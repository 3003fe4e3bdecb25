"""The robot-side speed limiter (bridge.core.limiter) on a fake clock: acceleration and jerk bounded per axis, a stop
exactly zero at once, never past the command, no limit configured = the command as it is; and the driver host's last
word: every driving decision limited, every stop immediate, the limited command echoed as ``clamped``."""

from __future__ import annotations

import math

import pytest

from bridge.core.gate import Decision
from bridge.core.limiter import AxisLimiter, SpeedLimiter
from bridge.nodes.driver_config import DEFAULT_HARD_LIMITS, DriverSection, HardLimits
from tests.fakeclock import FakeClock

DT = 0.02  # a 50 Hz host


def _run(lim: SpeedLimiter, clock: FakeClock, v: float, w: float, ticks: int) -> list[tuple[float, float]]:
    out = []
    for _ in range(ticks):
        out.append(lim.limit(v, w, clock.advance(DT)))
    return out


def test_a_step_ramps_at_the_acceleration_limit_and_reaches_the_command_exactly() -> None:
    clock = FakeClock()
    lim = SpeedLimiter(AxisLimiter(accel=1.0), AxisLimiter(accel=2.0), period=0.02)
    lim.stop(clock())
    out = _run(lim, clock, 0.5, 1.0, 40)
    vs, ws = [o[0] for o in out], [o[1] for o in out]
    assert vs[0] == pytest.approx(1.0 * DT) and ws[0] == pytest.approx(2.0 * DT)
    steps = [b - a for a, b in zip([0.0, *vs], vs)]
    assert max(steps) <= 1.0 * DT + 1e-12 and min(steps) >= 0.0  # never more than accel * dt, never back
    assert vs.index(0.5) in (24, 25) and ws.index(1.0) in (24, 25)  # 0.5 / (1.0 * 0.02) = 25 ticks (+ rounding)
    assert vs[-1] == 0.5 and ws[-1] == 1.0


def test_a_slow_down_is_ramped_too_but_a_stop_is_exactly_zero_at_once() -> None:
    clock = FakeClock()
    lim = SpeedLimiter(AxisLimiter(accel=1.0), AxisLimiter(accel=1.0))
    _run(lim, clock, 0.5, 0.5, 60)
    v, _ = lim.limit(0.1, 0.5, clock.advance(DT))
    assert v == pytest.approx(0.5 - DT)  # a driving command is ramped down as well
    assert lim.stop(clock.advance(DT)) == (0.0, 0.0)
    v, w = lim.limit(0.5, -0.5, clock.advance(DT))
    assert (v, w) == (pytest.approx(DT), pytest.approx(-DT))  # after a stop: from rest


def test_the_jerk_limit_bounds_the_change_of_acceleration_and_never_passes_the_command() -> None:
    clock = FakeClock()
    lim = SpeedLimiter(AxisLimiter(accel=2.0, jerk=5.0), AxisLimiter())
    lim.stop(clock())
    out = [o[0] for o in _run(lim, clock, 0.4, 0.0, 100)]
    vs = [0.0, *out]
    acc = [(b - a) / DT for a, b in zip(vs, vs[1:])]
    assert acc[0] == pytest.approx(5.0 * DT)  # the first step: jerk * dt of acceleration
    ramp = [a for a in acc if a > 0.0][:-1]  # (the last step lands on the command)
    assert all(b - a <= 5.0 * DT + 1e-9 for a, b in zip(ramp, ramp[1:]))
    assert max(acc) <= 2.0 + 1e-9
    assert max(out) == 0.4 and out[-1] == 0.4  # never past the command, and there at the end


def test_a_stalled_loop_gets_one_bounded_step_not_the_whole_gap() -> None:
    clock = FakeClock()
    lim = SpeedLimiter(AxisLimiter(accel=1.0), AxisLimiter(), period=0.02)
    lim.stop(clock())
    v, _ = lim.limit(1.0, 0.0, clock.advance(5.0))
    assert v == pytest.approx(0.04)


def test_without_limits_the_command_passes_as_it_is() -> None:
    clock = FakeClock()
    lim = DEFAULT_HARD_LIMITS.limiter(0.02)
    assert lim.unlimited
    assert lim.limit(0.5, -1.0, clock.advance(DT)) == (0.5, -1.0) and lim.limited == 0


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_a_limit_must_be_a_positive_number(bad: float) -> None:
    with pytest.raises(ValueError):
        AxisLimiter(accel=bad)


def test_the_configuration_keys_make_the_limiter_and_refuse_a_typo() -> None:
    import msgspec

    d = msgspec.convert({"hard_limits": {"v": [-1, 1], "w": [-2, 2], "v_accel": 0.8, "omega_jerk": 10.0}},
                        DriverSection)
    lim = d.hard_limits.limiter(0.02)
    assert (lim.v.accel, lim.v.jerk, lim.omega.accel, lim.omega.jerk) == (0.8, None, None, 10.0)
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"v": [-1, 1], "w": [-1, 1], "v_accel": -1.0}, HardLimits)


def test_the_driver_host_limits_every_driving_decision_and_echoes_it_as_clamped(tmp_path) -> None:
    """The host's last word (DriverHost.limited) on a host built from a configuration with the new keys: a step
    ramps, the echo is the limited command, a stop is exactly zero at once."""
    from bridge.nodes.driver_config import load_driver
    from bridge.nodes.driver_host import DriverHost

    cfg = tmp_path / "driver.toml"
    cfg.write_text("[driver.hard_limits]\nv = [-1.0, 1.0]\nw = [-1.0, 1.0]\nv_accel = 1.0\nomega_accel = 1.0\n")
    host = DriverHost(load_driver(cfg), "udp", driver=None, robot="r", rate_hz=50.0)  # type: ignore[arg-type]
    clock = FakeClock()
    got = [host.limited(Decision(1.0, -1.0, "cmd", 7), clock.advance(DT)) for _ in range(3)]
    assert [d.reason for d in got] == ["clamped"] * 3 and [d.cmd_seq for d in got] == [7] * 3
    assert [d.v for d in got] == pytest.approx([DT, 2 * DT, 3 * DT])
    assert [d.omega for d in got] == pytest.approx([-DT, -2 * DT, -3 * DT])
    stop = host.limited(Decision(0.0, 0.0, "stop", 8), clock.advance(DT))
    assert (stop.v, stop.omega, stop.reason) == (0.0, 0.0, "stop")
    again = host.limited(Decision(1.0, 0.0, "cmd", 9), clock.advance(DT))
    assert again.v == pytest.approx(DT) and again.omega == 0.0
