"""The lab's fence as ArduPilot's own (docs/ARCHITECTURE.md section 6, "The fence"): a polygon in the lab's frame
(the poses this driver publishes: ENU metres from the vehicle's EKF origin) uploaded as an inclusion polygon, so that
the autopilot holds the vehicle inside it even when the station and the driver host are gone.

Done only on a person's explicit request (``scmbridge driver --link mavlink --fence FILE``), after the link is open and
before anything is driven, and every step is confirmed by the vehicle or the upload fails (:class:`DriverError`):

1. the EKF origin: MAV_CMD_REQUEST_MESSAGE for GPS_GLOBAL_ORIGIN (its COMMAND_ACK read), then the message itself;
   each vertex is placed from it as ArduPilot's ``Location::offset`` does (its LOCATION_SCALING_FACTOR, the
   longitude scaled by the cosine of the latitude);
2. the polygon, by the MAVLink mission protocol with ``mission_type`` FENCE (ArduPilot's GCS_MAVLink mission
   protocol, AP_Mission's fence items): MISSION_COUNT, then one MISSION_ITEM_INT per MISSION_REQUEST_INT (or
   MISSION_REQUEST) the vehicle sends, each a MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION whose first parameter is
   the polygon's vertex count; the upload is done when the vehicle's MISSION_ACK says MAV_MISSION_ACCEPTED (any
   other MISSION_ACK fails it, with its name);
3. the fence's parameters by PARAM_SET, each confirmed by the PARAM_VALUE the vehicle answers with: FENCE_TYPE the
   polygon (bit 4: AC_Fence's AC_FENCE_TYPE_POLYGON), FENCE_ACTION Hold (Rover's FailsafeAction::Hold: at a breach,
   ``Rover::fence_check`` sets HOLD, and the vehicle stops), then FENCE_ENABLE 1;
4. MAV_CMD_DO_FENCE_ENABLE 1, its COMMAND_ACK read: ArduPilot answers FAILED until the fence is ``present()``
   (GCS_Fence.cpp), which for a polygon is once its loader has read the new polygon back from storage, so a FAILED
   is tried again each :data:`ENABLE_RETRY_S` until the timeout; any other refusal fails the upload.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from drivers.base import DriverError

#: metres per 1e-7 degree of latitude (ArduPilot's LOCATION_SCALING_FACTOR, libraries/AP_Common/Location.cpp)
LOCATION_SCALING_FACTOR = 0.011131884502145034
#: FENCE_TYPE's polygon bit (AC_Fence: AC_FENCE_TYPE_POLYGON)
FENCE_TYPE_POLYGON = 4
#: FENCE_ACTION on Rover: 2 is Hold (Rover.h FailsafeAction)
FENCE_ACTION_HOLD = 2
#: MAV_MISSION_TYPE_FENCE
MISSION_TYPE_FENCE = 1
#: s between two MAV_CMD_DO_FENCE_ENABLE the vehicle answered FAILED (its polygon not loaded yet)
ENABLE_RETRY_S = 0.5
#: the messages an upload reads (the driver hands them over while one runs)
FENCE_MESSAGES = ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK", "GPS_GLOBAL_ORIGIN", "PARAM_VALUE")


def to_global(origin: tuple[int, int], east: float, north: float) -> tuple[int, int]:
    """The latitude and longitude (1e-7 degree) ``east``, ``north`` metres from ``origin`` (1e-7 degree), as
    ArduPilot's ``Location::offset`` computes it."""
    lat0, lon0 = origin
    lat = lat0 + north / LOCATION_SCALING_FACTOR
    scale = max(math.cos(math.radians(lat0 * 1e-7)), 0.01)
    lon = lon0 + east / (LOCATION_SCALING_FACTOR * scale)
    lon = (lon + 1800000000) % 3600000000 - 1800000000
    return int(round(max(-900000000, min(900000000, lat)))), int(round(lon))


def check_polygon(polygon: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
    """The polygon as (east, north) pairs: at least 3 finite vertices, or :class:`DriverError`."""
    pts = [(float(p[0]), float(p[1])) for p in polygon]
    if len(pts) < 3 or not all(math.isfinite(a) and math.isfinite(b) for a, b in pts):
        raise DriverError(f"a fence needs at least 3 finite vertices, got {pts}")
    return pts


@dataclass
class FenceUpload:
    """What the vehicle said during one upload (fed by the driver's receive loop: :meth:`on_message`)."""

    target: tuple[int, int]
    origin: tuple[int, int] | None = None
    requested: list[int] = field(default_factory=list)  # seqs asked for, in order, not yet answered
    ack: int | None = None  # the MISSION_ACK's type for the fence
    params: dict[str, float] = field(default_factory=dict)

    def on_message(self, msg: Any) -> None:
        t = msg.get_type()
        if t == "GPS_GLOBAL_ORIGIN":
            self.origin = (int(msg.latitude), int(msg.longitude))
        elif t in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            if getattr(msg, "mission_type", 0) == MISSION_TYPE_FENCE:
                self.requested.append(int(msg.seq))
        elif t == "MISSION_ACK":
            if getattr(msg, "mission_type", 0) == MISSION_TYPE_FENCE:
                self.ack = int(msg.type)
        elif t == "PARAM_VALUE":
            name = str(msg.param_id).rstrip("\x00")
            if math.isfinite(msg.param_value):
                self.params[name] = float(msg.param_value)


def upload(driver: Any, polygon: Sequence[Sequence[float]], t_end: float) -> str:
    """Upload ``polygon`` (ENU metres from the EKF origin) as the vehicle's fence and enable it (the module
    docstring), through ``driver`` (a :class:`drivers.mavlink.driver.MavlinkDriver`, open) by ``t_end`` on its clock;
    what was done, in words. Raises :class:`DriverError` at the first step the vehicle does not confirm."""
    pts = check_polygon(polygon)
    client, mav = driver.client, driver.dialect.mav
    up = FenceUpload(driver.target)
    driver.fence_sink = up.on_message
    try:
        r = client.run(mav.MAV_CMD_REQUEST_MESSAGE, (mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,),
                       "GPS_GLOBAL_ORIGIN request", t_end)
        if r != mav.MAV_RESULT_ACCEPTED:
            raise DriverError(driver._refusal("the EKF origin's request", r, driver.client.now))
        if not client.wait(lambda: up.origin is not None, t_end):
            raise DriverError("no GPS_GLOBAL_ORIGIN from the vehicle: it has no EKF origin to place a fence from")
        items = [to_global(up.origin, e, n) for e, n in pts]  # type: ignore[arg-type]
        _send_polygon(driver, up, items, t_end)
        for name, value in (("FENCE_TYPE", FENCE_TYPE_POLYGON), ("FENCE_ACTION", FENCE_ACTION_HOLD),
                            ("FENCE_ENABLE", 1)):
            _set_param(driver, up, name, float(value), t_end)
        while True:  # refused (FAILED) until the vehicle has loaded the new polygon from its storage: tried again
            sent = driver.client.now
            r = client.run(mav.MAV_CMD_DO_FENCE_ENABLE, (1,), "fence enable", t_end)
            if r == mav.MAV_RESULT_ACCEPTED:
                break
            if r != mav.MAV_RESULT_FAILED or driver.client.now + ENABLE_RETRY_S >= t_end:
                raise DriverError(driver._refusal("fence enable", r, sent))
            client.wait(lambda: False, driver.client.now + ENABLE_RETRY_S)
    finally:
        driver.fence_sink = None
    lat, lon = up.origin
    return (f"fence of {len(pts)} vertices uploaded to the vehicle and enabled (FENCE_TYPE polygon, FENCE_ACTION "
            f"Hold; EKF origin {lat * 1e-7:.7f}, {lon * 1e-7:.7f})")


def _send_polygon(driver: Any, up: FenceUpload, items: list[tuple[int, int]], t_end: float) -> None:
    """The mission protocol's upload of the fence items: MISSION_COUNT (sent again while the vehicle asks nothing),
    each item the vehicle asks for, until its MISSION_ACK."""
    client, mav = driver.client, driver.dialect.mav
    tgt, n = driver.target, len(items)
    sent_count = -math.inf
    while up.ack is None:
        now = driver.client.now
        if now >= t_end:
            raise DriverError(f"fence upload: no MISSION_ACK from the vehicle ({len(up.requested)} items pending)")
        if not up.requested and now - sent_count >= driver.config.ack_timeout:
            client.send(lambda m: m.mission_count_send(tgt[0], tgt[1], n, MISSION_TYPE_FENCE))
            sent_count = now
        while up.requested:
            seq = up.requested.pop(0)
            if not 0 <= seq < n:
                raise DriverError(f"fence upload: the vehicle asked for item {seq} of {n}")
            lat, lon = items[seq]
            client.send(lambda m, s=seq, la=lat, lo=lon: m.mission_item_int_send(
                tgt[0], tgt[1], s, mav.MAV_FRAME_GLOBAL, mav.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 0, 0,
                float(n), 0.0, 0.0, 0.0, la, lo, 0.0, MISSION_TYPE_FENCE))
            sent_count = now
        client.wait(lambda: up.ack is not None or bool(up.requested), min(t_end, driver.client.now + 0.2))
    if up.ack != mav.MAV_MISSION_ACCEPTED:
        entry = mav.enums["MAV_MISSION_RESULT"].get(up.ack)
        raise DriverError(f"fence upload refused by the vehicle: {entry.name if entry else up.ack}")


def _set_param(driver: Any, up: FenceUpload, name: str, value: float, t_end: float) -> None:
    """PARAM_SET, sent again each ack_timeout until the vehicle's PARAM_VALUE says ``value``."""
    client, mav, tgt = driver.client, driver.dialect.mav, driver.target
    while driver.client.now < t_end:
        up.params.pop(name, None)
        client.send(lambda m: m.param_set_send(tgt[0], tgt[1], name.encode(), value, mav.MAV_PARAM_TYPE_REAL32))
        client.wait(lambda: name in up.params, min(t_end, driver.client.now + driver.config.ack_timeout))
        if name in up.params:
            if math.isclose(up.params[name], value, abs_tol=1e-6):
                return
            raise DriverError(f"{name} = {value:g} not taken: the vehicle says {up.params[name]:g}")
    raise DriverError(f"{name}: no PARAM_VALUE from the vehicle")


__all__ = ["FENCE_ACTION_HOLD", "FENCE_MESSAGES", "FENCE_TYPE_POLYGON", "LOCATION_SCALING_FACTOR",
           "MISSION_TYPE_FENCE", "FenceUpload", "check_polygon", "to_global", "upload"]
