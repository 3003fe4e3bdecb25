"""The emulated rover's fence (sim_learner/mavlink_fence.py), message by message as ArduPilot answers them: the fence
upload by the mission protocol, a malformed item refused, DO_FENCE_ENABLE only with a polygon present, a breach while
armed and enabled -> HOLD once. (The whole exchange with the real driver: tests/integration/test_fence_emulated.py.)"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from pymavlink.dialects.v20 import ardupilotmega as MAV

from drivers.mavlink.fence import to_global
from sim_learner.mavlink_fence import CMAC, EmulatedFence, inside, to_local

HOLD = 4


class Rover:
    """What the fence uses of the rover: its parameters, arming, pose, mode changes, texts and sends (recorded)."""

    def __init__(self) -> None:
        self.params: dict[str, float] = {}
        self.armed, self.origin, self.pose = False, True, (0.0, 0.0, 0.0)
        self.sent: list[tuple[str, tuple]] = []
        self.modes: list[int] = []
        self.texts: list[str] = []
        self.vehicle = SimpleNamespace(measured_pose=lambda now: self.pose)
        self.mav = SimpleNamespace(**{name: (lambda *a, n=name: self.sent.append((n, a))) for name in (
            "mission_request_int_send", "mission_ack_send", "gps_global_origin_send")})

    def has_origin(self, now: float) -> bool:
        return self.origin

    def _param_value(self, name: str) -> None:
        self.sent.append(("param_value", (name, self.params[name])))

    def _text(self, text: str, severity: int = 0) -> None:
        self.texts.append(text)

    def _set_mode(self, mode: int, now: float) -> bool:
        self.modes.append(mode)
        return True

    def _arm(self, arm: bool, now: float) -> int:
        self.armed = arm
        return 0


def _msg(kind: str, **fields):
    return SimpleNamespace(get_type=lambda: kind, get_srcSystem=lambda: 255, get_srcComponent=lambda: 190, **fields)


def _item(seq: int, n: int, east: float, north: float, command: int = MAV.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION):
    lat, lon = to_global(CMAC, east, north)
    return _msg("MISSION_ITEM_INT", seq=seq, command=command, param1=float(n), x=lat, y=lon, mission_type=1)


SQUARE = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]


def _upload(fence: EmulatedFence, rover: Rover, items) -> None:
    fence.handle(_msg("MISSION_COUNT", count=len(items), mission_type=1), 0.0)
    for item in items:
        fence.handle(item, 0.0)


def test_the_driver_places_a_vertex_where_the_vehicle_reads_it_back() -> None:
    for east, north in ((10.0, 0.0), (0.0, -25.0), (3.5, 7.25)):
        assert to_local(CMAC, *to_global(CMAC, east, north)) == pytest.approx((east, north), abs=0.01)
    assert inside(0.0, 0.0, SQUARE) and not inside(1.5, 0.0, SQUARE)


def test_an_upload_asks_for_each_item_and_acknowledges_the_polygon() -> None:
    rover = Rover()
    fence = EmulatedFence(rover, HOLD)
    _upload(fence, rover, [_item(k, 4, *p) for k, p in enumerate(SQUARE)])
    asked = [a[2] for n, a in rover.sent if n == "mission_request_int_send"]
    acks = [a[2] for n, a in rover.sent if n == "mission_ack_send"]
    assert asked == [0, 1, 2, 3] and acks == [MAV.MAV_MISSION_ACCEPTED]
    assert [c for p in fence.polygon for c in p] == pytest.approx([c for p in SQUARE for c in p], abs=0.01)


@pytest.mark.parametrize(("bad", "result"), [
    (_item(0, 3, 1.0, 1.0), MAV.MAV_MISSION_INVALID),  # param1 is not the vertex count
    (_item(0, 4, 1.0, 1.0, command=MAV.MAV_CMD_NAV_WAYPOINT), MAV.MAV_MISSION_UNSUPPORTED),
])
def test_a_malformed_item_fails_the_upload_and_keeps_the_old_polygon(bad, result) -> None:
    rover = Rover()
    fence = EmulatedFence(rover, HOLD)
    _upload(fence, rover, [bad])
    assert [a[2] for n, a in rover.sent if n == "mission_ack_send"] == [result] and fence.polygon == []


def test_enable_needs_a_polygon_and_a_breach_holds_the_rover_once() -> None:
    rover = Rover()
    fence = EmulatedFence(rover, HOLD)
    enable = (1.0, 0, 0, 0, 0, 0, 0)
    assert fence.command(MAV.MAV_CMD_DO_FENCE_ENABLE, enable, 0.0) == MAV.MAV_RESULT_FAILED  # nothing present
    _upload(fence, rover, [_item(k, 4, *p) for k, p in enumerate(SQUARE)])
    fence.handle(_msg("PARAM_SET", param_id="FENCE_TYPE", param_value=4.0), 0.0)
    assert ("param_value", ("FENCE_TYPE", 4.0)) in rover.sent
    assert fence.command(MAV.MAV_CMD_DO_FENCE_ENABLE, enable, 0.0) == MAV.MAV_RESULT_ACCEPTED
    rover.pose = (1.5, 0.0, 0.0)
    fence.check(1.0)
    assert rover.modes == []  # disarmed: no action
    rover.armed = True
    fence.check(2.0)
    fence.check(3.0)
    assert rover.modes == [HOLD] and fence.breaches == 1 and rover.texts == ["Fence Breached"]
    rover.pose = (0.0, 0.0, 0.0)
    fence.check(4.0)
    rover.pose = (0.0, 1.5, 0.0)
    fence.check(5.0)
    assert rover.modes == [HOLD, HOLD] and fence.breaches == 2  # back inside, out again: a new breach


def test_the_origin_is_sent_only_once_the_ekf_has_one() -> None:
    rover = Rover()
    fence = EmulatedFence(rover, HOLD)
    rover.origin = False
    ask = (float(MAV.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN), 0, 0, 0, 0, 0, 0)
    assert fence.command(MAV.MAV_CMD_REQUEST_MESSAGE, ask, 0.0) == MAV.MAV_RESULT_FAILED
    rover.origin = True
    assert fence.command(MAV.MAV_CMD_REQUEST_MESSAGE, ask, 0.0) == MAV.MAV_RESULT_ACCEPTED
    assert [a[:2] for n, a in rover.sent if n == "gps_global_origin_send"] == [CMAC]
    assert fence.command(MAV.MAV_CMD_NAV_WAYPOINT, ask, 0.0) is None  # not the fence's
