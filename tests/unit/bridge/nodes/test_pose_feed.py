"""The driver host's pose stream, pure (bridge/nodes/pose_feed.py): the link's poses or motion capture put on this
host's clock, numbered in the host's own stream, and the telemetry's age. Times are arguments (a fake clock)."""

from __future__ import annotations

import math

from bridge.core import wire as M
from bridge.nodes.pose_feed import PoseFeed
from drivers.base import Pose

EPOCH = 0xABC


def _mocap(stamp: float, x: float = 0.0) -> M.LearnerState:
    return M.LearnerState(stamp=stamp, seq=99, x=x, y=0.0, theta=0.0, epoch=1, source="bridge")


def test_the_links_poses_are_numbered_in_the_hosts_stream_and_keep_their_stamps() -> None:
    feed = PoseFeed("can", EPOCH)
    assert feed.age(5.0) == math.inf
    states = feed.states([Pose(1.0, 0.1, 0.2, 0.3, v=0.4), Pose(1.02, 0.2, 0.2, 0.3)], [])
    assert [(s.seq, s.stamp, s.epoch, s.source, s.x, s.v) for s in states] == [
        (0, 1.0, EPOCH, "can", 0.1, 0.4), (1, 1.02, EPOCH, "can", 0.2, None)]
    feed.published(1.0)
    assert feed.seq == 1 and feed.age(1.25) == 0.25
    feed.published(0.5)  # (an older tick's time never makes the telemetry look older)
    assert feed.seq == 2 and feed.last_pose == 1.0
    assert feed.states([Pose(1.1, 0.0, 0.0, 0.0)], [])[0].seq == 2


def test_motion_capture_is_put_on_this_hosts_clock_and_sorted_and_the_links_poses_dropped() -> None:
    """The bridge's clock runs 50 s behind this host's and its samples arrive 10-30 ms late: each sample gets
    ``stamp + offset``, the offset being the least ``receipt - stamp`` seen (the least latency, not each one's)."""
    feed = PoseFeed("mocap", EPOCH, mocap_window_s=5.0)
    assert feed.offer_mocap(_mocap(10.00, x=1.0), 60.01) == "ok"  # offset 50.01
    assert feed.offer_mocap(_mocap(9.99, x=0.5), 60.03) == "ok"  # later, out of order
    samples = feed.take_mocap()
    assert feed.take_mocap() == []
    states = feed.states([Pose(60.0, 9.0, 9.0, 0.0)], samples)  # the link's pose is not published
    assert [s.x for s in states] == [0.5, 1.0] and [s.seq for s in states] == [0, 1]
    assert all(s.source == "mocap" and s.epoch == EPOCH for s in states)
    assert all(s.stamp <= r for s, r in zip(states, (60.03, 60.01), strict=True))  # never after its receipt


def test_a_motion_capture_sample_stamped_ahead_of_any_delivery_is_dropped() -> None:
    feed = PoseFeed("mocap", EPOCH)
    for k in range(5):
        assert feed.offer_mocap(_mocap(10.0 + 0.01 * k), 60.01 + 0.01 * k) == "ok"
    feed.take_mocap()
    assert feed.offer_mocap(_mocap(20.0), 60.06) == "dropped"  # forged: 10 s ahead of the bridge's clock
    assert feed.take_mocap() == []


def test_the_vehicles_speed_is_measured_from_its_poses_or_taken_from_the_link() -> None:
    """What ``scmbridge status`` says moving or stopped from: a link's reported speeds where it gives them, else the
    poses' motion over at least MEASURE_WINDOW_S (a reversing vehicle has a negative speed)."""
    from bridge.nodes.pose_feed import MEASURE_WINDOW_S

    feed = PoseFeed("can", EPOCH)
    assert feed.measured is None
    t, x, th = 10.0, 0.0, 0.0
    for _ in range(20):  # 0.2 m/s forward, turning at 0.1 rad/s, poses at 50 Hz without speeds
        t, x, th = t + 0.02, x + 0.2 * 0.02, th + 0.1 * 0.02
        feed.published(t, M.LearnerState(stamp=t, seq=0, x=x, y=0.0, theta=th))
    v, omega = feed.measured
    assert abs(v - 0.2) < 0.02 and abs(omega - 0.1) < 0.01, feed.measured
    for _ in range(20):  # backwards
        t, x = t + 0.02, x - 0.1 * 0.02
        feed.published(t, M.LearnerState(stamp=t, seq=0, x=x, y=0.0, theta=th))
    assert feed.measured[0] < -0.05
    t += MEASURE_WINDOW_S
    feed.published(t, M.LearnerState(stamp=t, seq=0, x=x, y=0.0, theta=th, v=0.0, omega=0.0))  # the link's own
    assert feed.measured == (0.0, 0.0)
