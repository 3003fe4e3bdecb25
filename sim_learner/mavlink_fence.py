"""The emulated rover's geofence (sim_learner/mavlink_rover.py), written from ArduPilot's source, not from our driver
(paths in github.com/ArduPilot/ardupilot):

* The EKF origin (AP_AHRS, GCS_Common.cpp ``send_gps_global_origin``): MAV_CMD_REQUEST_MESSAGE for GPS_GLOBAL_ORIGIN
  sends it (latitude / longitude in 1e-7 degree; ``origin``, SITL's default home by default) once the EKF has an
  origin; before, the request fails.
* Fence upload by the mission protocol with ``mission_type`` FENCE (GCS_Common.cpp ``handle_mission_count`` /
  ``handle_mission_item``, MissionItemProtocol_Fence, AC_PolyFence_loader): MISSION_COUNT starts an upload and the
  vehicle asks for each item with MISSION_REQUEST_INT; each item
  must be MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION with the polygon's vertex count as param1 (else MISSION_ACK
  MAV_MISSION_INVALID, or MAV_MISSION_UNSUPPORTED for another command); an item out of order is asked for again;
  after the last, MISSION_ACK MAV_MISSION_ACCEPTED and the polygon replaces the stored one.
* PARAM_SET (GCS_Param.cpp ``handle_param_set``): a known parameter takes the value and the vehicle answers with its
  PARAM_VALUE; an unknown one is ignored. FENCE_ENABLE, FENCE_TYPE, FENCE_ACTION start as :data:`FENCE_DEFAULTS` (a
  vehicle whose fence nobody set up: disabled, no polygon type, Hold).
* MAV_CMD_DO_FENCE_ENABLE (GCS_Fence.cpp): 1 enables if a fence is ``present()`` (FENCE_TYPE's polygon bit with an
  inclusion polygon loaded), else MAV_RESULT_FAILED; 0 disables.
* The check (Rover/fence.cpp ``fence_check``, at 10 Hz): while armed and enabled, the vehicle outside the polygon is a
  new breach; with FENCE_ACTION not 0 (report only) the vehicle goes to HOLD and stops (RTL and SmartRTL are not
  modelled: HOLD, their own fallback; Terminate disarms). A breach is recorded once until the vehicle is inside again.

Not modelled: Rover's avoidance (AC_Avoid, on by default with a fence), which in the firmware slows the vehicle to a
stop its margin inside the fence before any breach; here the vehicle reaches the line and then holds. Circles, altitude
fences, exclusion zones and the return point are not modelled either.
"""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as MAV

#: SITL's default home (CMAC), 1e-7 degree: the EKF origin this emulated vehicle reports
CMAC = (-353632640, 1491652352)
#: m per 1e-7 degree of latitude (ArduPilot's LOCATION_SCALING_FACTOR)
LOCATION_SCALING_FACTOR = 0.011131884502145034
FENCE_TYPE_POLYGON = 4
MISSION_TYPE_FENCE = 1
#: Rover: FENCE_ENABLE, FENCE_TYPE, FENCE_ACTION as an emulated vehicle starts (nothing set up)
FENCE_DEFAULTS = {"FENCE_ENABLE": 0.0, "FENCE_TYPE": 0.0, "FENCE_ACTION": 2.0}
#: the fence is checked this often, s (Rover's 10 Hz)
CHECK_PERIOD_S = 0.1


def to_local(origin: tuple[int, int], lat: int, lon: int) -> tuple[float, float]:
    """(east, north) metres of ``(lat, lon)`` (1e-7 degree) from ``origin``, as ArduPilot's Location does."""
    scale = max(math.cos(math.radians(origin[0] * 1e-7)), 0.01)
    dlon = (lon - origin[1] + 1800000000) % 3600000000 - 1800000000
    return dlon * LOCATION_SCALING_FACTOR * scale, (lat - origin[0]) * LOCATION_SCALING_FACTOR


def inside(x: float, y: float, polygon: list[tuple[float, float]]) -> bool:
    """Even-odd rule (AP_Math ``Polygon_outside``'s)."""
    hit = False
    for i, (ax, ay) in enumerate(polygon):
        bx, by = polygon[(i + 1) % len(polygon)]
        if (ay > y) != (by > y) and x < ax + (y - ay) * (bx - ax) / (by - ay):
            hit = not hit
    return hit


class EmulatedFence:
    """The fence of one :class:`sim_learner.mavlink_rover.MavlinkRover` (the module docstring). Runs on the rover's
    thread: :meth:`handle` and :meth:`command` from its message handling, :meth:`check` from its update."""

    def __init__(self, rover: Any, hold_mode: int, origin: tuple[int, int] = CMAC) -> None:
        self.rover, self.hold_mode = rover, int(hold_mode)
        self.origin = origin
        for name, value in FENCE_DEFAULTS.items():
            rover.params.setdefault(name, value)
        self.polygon: list[tuple[float, float]] = []  # the stored inclusion polygon, ENU metres from the origin
        self.enabled = False
        self.breached = False
        self.breaches = 0
        self._upload: dict[str, Any] | None = None  # count, items, the next seq, the uploader, when asked last
        self._next_check = 0.0

    # ------------------------------------------------------------------------------------------- messages
    def handle(self, msg: Any, now: float) -> bool:
        """A message for the fence (True: handled)."""
        t = msg.get_type()
        if t == "MISSION_COUNT" and getattr(msg, "mission_type", 0) == MISSION_TYPE_FENCE:
            self._upload = {"count": int(msg.count), "items": [], "seq": 0, "to": (msg.get_srcSystem(),
                                                                                   msg.get_srcComponent())}
            if msg.count == 0:
                self._finish(MAV.MAV_MISSION_ACCEPTED)
            else:
                self._request(now)
            return True
        if t in ("MISSION_ITEM_INT", "MISSION_ITEM") and getattr(msg, "mission_type", 0) == MISSION_TYPE_FENCE:
            self._item(msg, now)
            return True
        if t == "PARAM_SET":
            name = str(msg.param_id).rstrip("\x00")
            if name in self.rover.params and math.isfinite(msg.param_value):
                self.rover.params[name] = float(msg.param_value)
                self.rover._param_value(name)
            return True
        return False

    def _request(self, now: float) -> None:
        up = self._upload
        assert up is not None
        self.rover.mav.mission_request_int_send(up["to"][0], up["to"][1], up["seq"], MISSION_TYPE_FENCE)
        up["asked"] = now

    def _item(self, msg: Any, now: float) -> None:
        up = self._upload
        if up is None:
            return
        if int(msg.seq) != up["seq"]:  # out of order: ask again for the one expected
            self._request(now)
            return
        if int(msg.command) != MAV.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION:
            self._finish(MAV.MAV_MISSION_UNSUPPORTED)
            return
        if int(msg.param1) != up["count"] or not math.isfinite(msg.param1):
            self._finish(MAV.MAV_MISSION_INVALID)
            return
        lat, lon = (int(msg.x), int(msg.y)) if msg.get_type() == "MISSION_ITEM_INT" else (
            int(round(msg.x * 1e7)), int(round(msg.y * 1e7)))
        up["items"].append(to_local(self.origin, lat, lon))
        up["seq"] += 1
        if up["seq"] < up["count"]:
            self._request(now)
        else:
            self.polygon = list(up["items"])
            self._finish(MAV.MAV_MISSION_ACCEPTED)

    def _finish(self, result: int) -> None:
        up = self._upload
        assert up is not None
        self.rover.mav.mission_ack_send(up["to"][0], up["to"][1], result, MISSION_TYPE_FENCE)
        self._upload = None

    def command(self, command: int, p: tuple[float, ...], now: float) -> int | None:
        """A COMMAND_LONG for the fence: its MAV_RESULT (None: not the fence's)."""
        if command == MAV.MAV_CMD_REQUEST_MESSAGE and int(p[0]) == MAV.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            if not self.rover.has_origin(now):
                return MAV.MAV_RESULT_FAILED
            self.rover.mav.gps_global_origin_send(self.origin[0], self.origin[1], 0, int(now * 1e6))
            return MAV.MAV_RESULT_ACCEPTED
        if command == MAV.MAV_CMD_DO_FENCE_ENABLE:
            if p[0] == 0.0:
                self.enabled = False
                return MAV.MAV_RESULT_ACCEPTED
            if p[0] == 1.0:
                if not self.present:
                    return MAV.MAV_RESULT_FAILED
                self.enabled = True
                return MAV.MAV_RESULT_ACCEPTED
            return MAV.MAV_RESULT_FAILED
        return None

    @property
    def present(self) -> bool:
        return bool(int(self.rover.params["FENCE_TYPE"]) & FENCE_TYPE_POLYGON) and len(self.polygon) >= 3

    @property
    def active(self) -> bool:
        """Checked now: enabled (the command or FENCE_ENABLE), present, the vehicle armed."""
        return (self.enabled or bool(self.rover.params["FENCE_ENABLE"])) and self.present and self.rover.armed

    # ------------------------------------------------------------------------------------------- the check
    def next_check(self) -> float:
        """When :meth:`check` has something to do next (inf: nothing while inactive)."""
        return self._next_check if self.active else math.inf

    def check(self, now: float) -> None:
        """``Rover::fence_check``: a new breach takes FENCE_ACTION."""
        if now < self._next_check:
            return
        self._next_check = now + CHECK_PERIOD_S
        if not self.active:
            return
        x, y, _ = self.rover.vehicle.measured_pose(now)
        if inside(x, y, self.polygon):
            self.breached = False
            return
        if self.breached:
            return
        self.breached = True
        self.breaches += 1
        self.rover._text("Fence Breached", MAV.MAV_SEVERITY_CRITICAL)
        action = int(self.rover.params["FENCE_ACTION"])
        if action == 5:  # Terminate
            self.rover._arm(False, now)
        elif action != 0:  # RTL, Hold, SmartRTL, SmartRTL_Hold: HOLD (RTL and SmartRTL are not modelled)
            self.rover._set_mode(self.hold_mode, now)


__all__ = ["CMAC", "EmulatedFence", "FENCE_DEFAULTS", "inside", "to_local"]
