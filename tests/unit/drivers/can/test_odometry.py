"""The CAN link's odometry without a bus: encoder estimates (rev, rev/s, stamp) in, differential-drive poses out,
and the checks that keep an implausible estimate out of the pose (too fast, too far, more travel than the budget,
or a real encoder jump that re-anchors the reference)."""

from __future__ import annotations

import math

import pytest

from drivers.can.odometry import BURST_S, COMMAND_SLACK_REV_S, Odometry, Wheel

RADIUS, TRACK = 0.1, 0.4
CIRC = 2 * math.pi * RADIUS


def odometry(max_wheel_speed: float = 5.0) -> Odometry:
    return Odometry(RADIUS, TRACK, max_wheel_speed, Wheel(1.0), Wheel(-1.0), (0.0, 0.0, 0.0))


def feed(o: Odometry, left: float, right: float, t: float, vl: float = 0.0, vr: float = 0.0):
    """Both wheels' estimates at ``t``; the step the second one completes."""
    assert not o.estimate(o.left, left, vl, t).rejected
    return o.estimate(o.right, right, vr, t)


def test_straight_and_turning_steps_integrate_with_the_mirrored_right_motor() -> None:
    o = odometry()
    o.left.commanded = o.right.commanded = 2.0
    assert feed(o, 0.0, 0.0, 0.0).pose is None  # the anchors
    step = feed(o, 0.1, -0.1, 0.1, vl=1.0, vr=-1.0)  # both wheels forward 0.1 rev
    assert step.pose is not None and step.pose.x == pytest.approx(0.1 * CIRC) and step.pose.y == 0.0
    assert step.pose.v == pytest.approx(CIRC) and step.pose.omega == pytest.approx(0.0) and step.pose.stamp == 0.1
    turn = feed(o, 0.1, -0.2, 0.2, vl=0.0, vr=-1.0).pose  # only the right wheel: a left turn about the left one
    assert turn is not None and turn.theta == pytest.approx(0.1 * CIRC / TRACK) and turn.y > 0.0
    assert turn.omega == pytest.approx(CIRC / TRACK)
    assert o.wheel_turn_rates(CIRC, 0.0) == pytest.approx((1.0, -1.0))


def test_an_estimate_too_fast_or_too_far_is_rejected_and_never_integrated() -> None:
    o = odometry()
    feed(o, 0.0, 0.0, 0.0)
    assert o.estimate(o.left, 0.0, 6.0, 0.01).rejected  # |Vel_Estimate| above max_wheel_speed
    assert o.estimate(o.left, 2e7, 0.0, 0.01).rejected  # |Pos_Estimate| beyond any encoder
    step = o.estimate(o.left, 1.0, 0.0, 0.01)  # 1 rev in 10 ms: 100 rev/s
    assert step.rejected and not step.overrun and not step.resynced and o.pose == [0.0, 0.0, 0.0]


def test_many_small_plausible_steps_cannot_outrun_the_travel_budget() -> None:
    """A wheel told to stand still may turn COMMAND_SLACK_REV_S at most: crafted frames at 2 kHz, each step plausible
    alone, stop being integrated once the budget is spent."""
    o = odometry()
    feed(o, 0.0, 0.0, 0.0)
    accepted, t, pos = 0, 0.0, 0.0
    for _ in range(400):  # 0.2 s of frames, 0.004 rev each (8 rev/s asked, under max_wheel_speed per step)
        t += 0.0005
        pos += 0.004
        step = o.estimate(o.left, pos, 0.0, t)
        if step.overrun:
            assert step.rejected
            break
        accepted += 1
    # stopped within the budget: a burst's worth plus the refill over the frames' span, not the 1.6 rev they claimed
    assert 0 < accepted < 400 and accepted * 0.004 <= COMMAND_SLACK_REV_S * (BURST_S + t) + 1e-9, accepted
    assert o.left.new is not None and o.left.new[0] == pytest.approx(accepted * 0.004)


def test_agreeing_rejected_steps_re_anchor_the_reference_without_moving_the_pose() -> None:
    o = odometry()
    o.left.commanded = o.right.commanded = 1.0
    t = 0.0
    for k in range(5):
        t = 0.01 * k
        feed(o, 0.01 * k, -0.01 * k, t, 1.0, -1.0)
    x = o.pose[0]
    steps = []
    for k in range(1, 4):  # the left controller rebooted: its position starts again near 500 rev
        t += 0.01
        steps.append(o.estimate(o.left, 500.0 + 0.01 * k, 1.0, t))
        o.estimate(o.right, -0.04 - 0.01 * k, -1.0, t)
    assert [s.rejected for s in steps] == [True] * 3 and [s.resynced for s in steps] == [False, False, True]
    assert o.pose[0] == pytest.approx(x, abs=1e-9) and o.left.pos == pytest.approx(500.03)


def test_estimates_read_late_are_judged_by_the_command_in_force_when_they_were_measured() -> None:
    """Finding (a fresh clone's suite beside two busy loops): a loaded driver host read a second of encoder frames
    after it had already sent the stop, judged the wheel's travel by the stop (0.5 rev/s of slack) instead of the
    1 rev/s it was turning at, called the encoder implausible and the station paused the mission."""
    o = odometry()
    o.command(o.left, 1.0, 0.0)
    o.command(o.right, -1.0, 0.0)
    feed(o, 0.0, 0.0, 0.0)
    o.command(o.left, 0.0, 1.0)  # the stop, sent before the frames below are read
    o.command(o.right, 0.0, 1.0)
    for k in range(1, 101):  # the frames of the second before the stop: 1 rev/s, every one plausible
        t = 0.01 * k
        step = feed(o, t, -t, t, 1.0, -1.0)
        assert not step.rejected and step.pose is not None, k
    # after the stop (and its BURST_S of response), the same speed is more than the wheel was told
    steps = [o.estimate(o.left, 1.0 + 0.01 * k, 1.0, 1.0 + BURST_S + 0.01 * k) for k in range(1, 40)]
    assert any(s.overrun for s in steps)


def test_a_stop_written_late_leaves_the_old_command_in_force_until_the_frame_left() -> None:
    """A driver host preempted between deciding a stop (at its tick's start) and writing it to the bus: the
    controllers keep turning at the old speed until the frame arrives and report it, stamped by the kernel as
    they come. The wheel is judged by the old command until the frame left, by the stop after it."""

    def run(sent: float | None) -> list[bool]:
        o = odometry()
        o.command(o.left, 2.0, 0.0)
        feed(o, 0.0, 0.0, 0.0)
        o.command(o.left, 0.0, 0.01, sent)  # decided at 0.01, on the bus at ``sent``
        return [o.estimate(o.left, 0.02 * k, 2.0, 0.01 * k).overrun for k in range(1, 51)]  # 2 rev/s until 0.5 s

    assert not any(run(sent=0.5))
    assert any(run(sent=None))  # the same frames judged by the stop from the moment it was decided
    o = odometry()
    o.command(o.left, 2.0, 0.0)
    feed(o, 0.0, 0.0, 0.0)
    o.command(o.left, 0.0, 0.01, 0.2)
    assert any(o.estimate(o.left, 0.02 * k, 2.0, 0.01 * k).overrun for k in range(1, 100))  # and it ends


def test_a_wheels_command_memory_keeps_the_command_in_force_and_forgets_older_ones() -> None:
    o = odometry()
    for k in range(50):
        o.command(o.left, float(k % 3), 0.1 * k)
    assert o.left.history[0][0] <= 4.9 - 2.0 <= o.left.history[1][0]  # the one in force when the memory starts
    assert o.left.commanded == float(49 % 3)
