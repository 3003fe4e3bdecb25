"""``[link.can]``: the CAN link's configuration (read without importing python-can or cantools)."""

from __future__ import annotations

from typing import Annotated

from bridge.core.config import Cfg, Finite, Rule, meta


class CanLinkConfig(Cfg):
    """``[link.can]``: a differential-drive base with one ODrive 0.6 (CANSimple) controller per wheel."""

    interface: Annotated[str, meta("python-can interface: socketcan, virtual, udp_multicast, pcan, ...")] = "socketcan"
    channel: Annotated[str, meta("bus channel: can0, a virtual channel name, a multicast group", min_length=1)] = "can0"
    bitrate: Annotated[int, meta("bit/s (ignored by socketcan: set it with `ip link`)", ge=10_000, le=8_000_000)] = (
        500_000)
    fd: Annotated[bool, meta("CAN FD (udp_multicast needs an explicit false)")] = False
    left_node: Annotated[int, meta("left wheel's CANSimple node id", ge=0, le=63)] = 0
    right_node: Annotated[int, meta("right wheel's CANSimple node id", ge=0, le=63)] = 1
    left_sign: Annotated[float, meta("+1 or -1: -1 for a mirrored motor")] = 1.0
    right_sign: Annotated[float, meta("+1 or -1: -1 for a mirrored motor")] = -1.0
    wheel_radius: Annotated[float, meta("m", gt=0.0, le=10.0)] = 0.1
    track_width: Annotated[float, meta("distance between the wheels, m", gt=0.0, le=100.0)] = 0.4
    initial_pose: Annotated[tuple[Finite, Finite, Finite], meta("odometry origin [x, y, theta]")] = (0.0, 0.0, 0.0)
    open_timeout: Annotated[float, meta("s to wait for both axes in closed loop (at open and after clear_faults)",
                                        gt=0.0, le=120.0)] = 2.0
    heartbeat_timeout: Annotated[float, meta(
        "s without a controller's Heartbeat before the link is reported lost and the other wheel stopped (ODrive sends "
        "one every 0.1 s by default; keep it at or below the controllers' watchdog_timeout)", ge=0.05, le=10.0)] = 0.5
    max_wheel_speed: Annotated[float, meta("rev/s: an encoder estimate faster than this, or a position step it cannot "
                                           "explain, is rejected as implausible", gt=0.0, le=1000.0)] = 5.0
    reopen_backoff: Annotated[float, meta("s before the first attempt to reopen a failed bus; doubles per failed "
                                          "attempt", gt=0.0, le=10.0)] = 0.1
    reopen_backoff_max: Annotated[float, meta("s: the longest wait between two attempts to reopen a failed bus",
                                              gt=0.0, le=60.0)] = 2.0

    def __post_init__(self) -> None:
        if self.reopen_backoff_max < self.reopen_backoff:
            raise Rule(f"reopen_backoff_max = {self.reopen_backoff_max} < reopen_backoff = "
                             f"{self.reopen_backoff}: the longest wait cannot be shorter than the first")
        if self.left_node == self.right_node:
            raise Rule(f"left_node and right_node are both {self.left_node}; each wheel needs its own node")
        for name in ("left_sign", "right_sign"):
            if getattr(self, name) not in (1.0, -1.0):
                raise Rule(f"{name} = {getattr(self, name)}: must be 1 or -1")
