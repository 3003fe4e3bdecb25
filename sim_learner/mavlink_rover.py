"""An emulated ArduPilot Rover (4.x) on MAVLink 2, driving the software learner.

It is written from ArduPilot's published source and documentation, not from our driver, so that a test catches a
driver that is wrong about the vehicle. Paths are in github.com/ArduPilot/ardupilot; what it does and where from:

* Boot (Rover/system.cpp ``init_ardupilot``, AP_Vehicle.cpp ``scheduler_delay_callback``): the vehicle reports mode
  INITIALISING (16) for ``init_s`` seconds while it still answers MAVLink from its delay callback, then switches to
  INITIAL_MODE (0, MANUAL) whatever a ground station set meanwhile: a GUIDED set during boot is acknowledged and lost.
* Position (Rover/ekf_check.cpp ``ekf_position_ok``, GCS_Common.cpp ``send_local_position``): the EKF has a position
  estimate ``ekf_position_s`` after boot and an origin ``ekf_origin_s`` after boot (default: the same moment, the
  GPS case; ``math.inf``: never, a rover without GPS whose origin nobody sets). LOCAL_POSITION_NED is only sent once
  there is an origin.
* MAV_CMD_DO_SET_MODE (GCS_Common.cpp ``_set_mode_common``, Rover/system.cpp ``Rover::set_mode``, Rover/mode.cpp
  ``Mode::enter``): param1 needs MAV_MODE_FLAG_CUSTOM_MODE_ENABLED (else MAV_RESULT_DENIED); a number Rover has no mode
  for -> MAV_RESULT_FAILED and STATUSTEXT "No such mode N" (AP_Vehicle::notify_no_such_mode); while armed a mode that
  needs a position is refused without one (FAILED, "Flight mode change failed"); while disarmed every mode is entered
  ("we rely on the arming check"). A mode change sends a HEARTBEAT at once. Entering GUIDED starts stopped
  (Rover/mode_guided.cpp ``_enter`` -> ``start_stop``).
* MAV_CMD_COMPONENT_ARM_DISARM (GCS_Common.cpp ``handle_command_component_arm_disarm``, Rover/AP_Arming.cpp): already
  in the asked state -> ACCEPTED; arming runs the pre-arm checks and a failure is MAV_RESULT_FAILED with a STATUSTEXT
  "PreArm: ..." ("Hardware safety switch" while ``safety_switch`` is on, "Mode not armable" while initialising, "Need
  Position Estimate" when the mode needs a position the EKF does not have). The STATUSTEXT leaves through
  ArduPilot's text queue, i.e. *after* the COMMAND_ACK. Success says "Throttle armed" / "Throttle disarmed".
* MAV_CMD_SET_MESSAGE_INTERVAL (GCS_Common.cpp ``set_message_interval``): microseconds -> milliseconds, -1 stops the
  message, 0 restores its default, a message the vehicle cannot stream -> MAV_RESULT_FAILED. Streams start at the
  SRx defaults (1 Hz, Rover/GCS_Mavlink.cpp).
* Every COMMAND_LONG / COMMAND_INT gets one COMMAND_ACK addressed to its sender (target_system / target_component, as
  ArduPilot fills them since PR #21720); other commands -> MAV_RESULT_UNSUPPORTED. Commands and set-points addressed to
  another system or component are not for this vehicle (MAVLink routing) and are ignored.
* SET_POSITION_TARGET_LOCAL_NED (Rover/GCS_Mavlink.cpp ``handle_set_position_target_local_ned``; "Rover Commands in
  Guided Mode", https://ardupilot.org/dev/docs/mavlink-rover-commands.html): silently ignored outside GUIDED and
  until the EKF has an origin; frames LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED; Rover/defines.h masks
  (position bits 0-1, velocity bits 3-4, acceleration bits 6-7, yaw bit 10, yaw rate bit 11). Velocity + yaw rate:
  speed |(vx, vy)| capped at WP_SPEED, driving backwards when vx < 0; turn rate yaw_rate (clockwise positive), capped
  here at ATC_STR_RAT_MAX (``str_rat_max``, rad/s). Disarmed, the target is taken but the motors do not turn.
  Non-finite values never reach the motors, as in ArduPilot's arithmetic: the speed is ``safe_sqrt(vx^2 + vy^2)``
  (AP_Math: a NaN root is 0, so a NaN velocity is a stop; an infinite one is WP_SPEED), and a NaN turn rate goes
  through ``constrain_float`` (AP_Math: a NaN becomes the middle of its range and raises the internal error
  ``constraining_nan``; in AR_AttitudeControl ``get_steering_out_rate`` that range is the acceleration limit around
  the last desired rate, so the last turn rate is kept; +-inf become +-ATC_STR_RAT_MAX).
* Stopping: a zero target (or a GUID_TIMEOUT stop) brakes at ``decel_max`` m/s^2 (ATC_DECEL_MAX; Rover's speed
  controller limits deceleration, AR_AttitudeControl ``get_throttle_out_speed``); disarmed, the motors are off and the
  rover coasts, slowing at ``coast_decel`` m/s^2 (friction). Other targets are taken at once (the learner's response
  models its dynamics).
* GUID_TIMEOUT (Rover/mode_guided.cpp): no new target for ``guid_timeout`` s (3 by default) -> STATUSTEXT "target not
  received last 3secs, stopping" (the firmware's words, as SITL sends them) and a stop.
* Signing (libraries/GCS_MAVLink/GCS_Signing.cpp): :mod:`sim_learner.mavlink_signing` (the C library's check
  order, the timestamp kept across a reboot, the GPS's time).
* Parameters (Rover/Parameters.cpp defaults: FS_ACTION 2 = Hold, FS_TIMEOUT 1.5 s, FS_GCS_ENABLE 0, FS_GCS_TIMEOUT 5 s;
  SYSID_MYGCS 255; and what it models under Rover's names: WP_SPEED = ``wp_speed``, ATC_STR_RAT_MAX = ``str_rat_max``
  in deg/s, ATC_DECEL_MAX = ``decel_max``, as a ground station reads the learner's range): PARAM_REQUEST_READ by
  name (index -1) or index, and PARAM_REQUEST_LIST, answered with PARAM_VALUE (REAL32); an unknown name gets no
  answer, as in AP_Param.
* GCS failsafe (Rover/Rover.cpp ``gcs_failsafe_check``, Rover/failsafe.cpp ``failsafe_trigger``): with FS_GCS_ENABLE
  set, no HEARTBEAT from the ground station (system SYSID_MYGCS) for FS_GCS_TIMEOUT starts the failsafe; if it
  persists FS_TIMEOUT while armed, FS_ACTION is taken (1 RTL, modelled as Hold since RTL is not; 2 Hold; 0 nothing)
  with STATUSTEXT "Failsafe: GCS". A HEARTBEAT ends it (the mode stays: the operator takes the vehicle back).
* HEARTBEAT at 1 Hz: GROUND_ROVER, ARDUPILOTMEGA, base_mode and system_status as Rover/GCS_Mavlink.cpp ``base_mode``
  / ``vehicle_system_status`` (CUSTOM_MODE_ENABLED, GUIDED_ENABLED in autopilot modes, SAFETY_ARMED; CALIBRATING while
  initialising, STANDBY in HOLD, else ACTIVE).
* Transport: :mod:`sim_learner.mavlink_rover_link` (udp like a telemetry bridge, tcp like SITL's serial port).

Measured against the firmware itself (ArduPilot Rover 4.7.0-dev SITL, rover-skid, stock parameters, 2026-11-27; the
same scenarios run on both in tests/integration/test_sitl.py, and the figures below with a ground station on each
vehicle's link, one run each): mode names and numbers, the COMMAND_ACKs (an unknown mode: FAILED, then "No such
mode 77"), the GUIDED timeout (its text 2.9 s after the last set-point on both), FS_ACTION 2 / FS_TIMEOUT 1.5 /
FS_GCS_ENABLE 0 and a stopped rover after HOLD agree. What differs, and stays so on purpose:

* Boot: SITL reaches a healthy EKF in ~4 s of wall time at speedup 10 (its GPS comes at 9.6 s at speedup 1); here
  ``init_s`` and ``ekf_position_s`` (0.3 s and 1 s by default) so that tests are fast.
* Braking: SITL brakes at ATC_ACCEL_MAX (1 m/s^2; ATC_DECEL_MAX 0 means "the same") behind its speed filter: 0.6 m/s
  to below 0.05 m/s in 0.95 s on a zero set-point, 0.75 s on HOLD, GUIDED timeout to stopped 3.75 s; here
  ``decel_max`` 2 m/s^2 by default (0.4 s, 0.31 s, 3.2 s). Tests that need the firmware's figure pass
  ``decel_max=1.0``.
* Coasting: SITL's simulated body has no inertia of its own (its speed follows the throttle with a ~0.3 s lag), so a
  rover disarmed at 0.6 m/s is still in 0.67 s, faster than it brakes; here it coasts at ``coast_decel`` 0.3 m/s^2
  (1.9 s), as a real rover rolls on: a driver that disarms before the rover stops is caught here, not in SITL.
* Parameters: SITL answers every parameter of the firmware; here only FS_*, WP_SPEED, ATC_STR_RAT_MAX,
  ATC_DECEL_MAX, FENCE_ENABLE/TYPE/ACTION and SYSID_MYGCS, which Rover 4.7 no longer has (SITL gives no PARAM_VALUE
  for it).
* The fence (:mod:`sim_learner.mavlink_fence`: the EKF origin, the fence upload, DO_FENCE_ENABLE, a breach -> HOLD):
  SITL's avoidance (on by default with a fence) stops the rover its margin (about 2 m) inside the fence before any
  breach; here it reaches the line and holds there.
* The pilot: SITL has a ground station port (SERIAL0) beside the driver's; here there is one link, and the person's
  switches are :meth:`rc_mode_switch` / :meth:`rc_arm`.

The operator's side: :meth:`rc_mode_switch` and :meth:`rc_arm` do what a transmitter's mode switch and arming switch
do; :meth:`radio_blackout` cuts the link both ways; :meth:`foreign` sends as another system on the same link. Frames:
NED (x north, y east, yaw clockwise from north) on the wire, ENU in :class:`sim_learner.vehicle.SimVehicle`.
"""

from __future__ import annotations

import math
import os
import queue
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from pymavlink import mavutil

from sim_learner.device import ThreadedDevice
from sim_learner.mavlink_dialect import MAV
from sim_learner.mavlink_fence import EmulatedFence
from sim_learner.mavlink_rover_link import LinkMixin, Tx
from sim_learner.mavlink_signing import SIGNING_SAVE_S, SigningMixin
from sim_learner.vehicle import SimVehicle

#: the parameters this vehicle answers for, with Rover's defaults (Rover/Parameters.cpp, GCS_MAVLink)
PARAM_DEFAULTS: dict[str, float] = {"FS_ACTION": 2.0, "FS_TIMEOUT": 1.5, "FS_GCS_ENABLE": 0.0, "FS_GCS_TIMEOUT": 5.0,
                                    "SYSID_MYGCS": 255.0}
#: Rover's mode numbers (Rover/mode.h), by name, from pymavlink's table.
MODES: dict[str, int] = mavutil.mode_mapping_byname(MAV.MAV_TYPE_GROUND_ROVER)
MODE_NAMES: dict[int, str] = mavutil.mode_mapping_bynumber(MAV.MAV_TYPE_GROUND_ROVER)
MANUAL, HOLD, GUIDED, INITIALISING = MODES["MANUAL"], MODES["HOLD"], MODES["GUIDED"], MODES["INITIALISING"]
#: Modes ``Rover::mode_from_mode_num`` knows (2, LEARNING, is gone from Rover 4).
ROVER_MODES = frozenset(n for n in MODE_NAMES if n != 2)
#: ``requires_position()`` in Rover/mode.h.
NEEDS_POSITION = frozenset(MODES[n] for n in ("AUTO", "GUIDED", "LOITER", "FOLLOW", "RTL", "SMART_RTL", "CIRCLE",
                                              "DOCK") if n in MODES)
#: ``is_autopilot_mode()``: HEARTBEAT base_mode carries MAV_MODE_FLAG_GUIDED_ENABLED.
AUTOPILOT_MODES = NEEDS_POSITION
#: ``has_manual_input()``: MAV_MODE_FLAG_MANUAL_INPUT_ENABLED.
MANUAL_INPUT_MODES = frozenset(MODES[n] for n in ("MANUAL", "ACRO", "STEERING", "HOLD", "SIMPLE") if n in MODES)

VELOCITY_YAWRATE_MASK = 0x05E7  # the docs' "Use Vel+Yaw Rate"
_POS_IGNORE, _VEL_IGNORE, _ACC_IGNORE = 0x0003, 0x0018, 0x00C0  # Rover/defines.h MAVLINK_SET_POS_TYPE_MASK_*
_YAW_IGNORE, _YAW_RATE_IGNORE = 0x0400, 0x0800
_FRAMES = (MAV.MAV_FRAME_LOCAL_NED, MAV.MAV_FRAME_LOCAL_OFFSET_NED, MAV.MAV_FRAME_BODY_NED,
           MAV.MAV_FRAME_BODY_OFFSET_NED)
#: Messages this vehicle can stream at a requested interval (the others ArduPilot knows are accepted but not sent
#: here); anything else is refused like a message ArduPilot has no ``ap_message`` for.
_STREAMED = {MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0, MAV.MAVLINK_MSG_ID_ATTITUDE: 1.0}
_KNOWN = {MAV.MAVLINK_MSG_ID_HEARTBEAT, MAV.MAVLINK_MSG_ID_SYS_STATUS, MAV.MAVLINK_MSG_ID_GPS_RAW_INT,
          MAV.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, MAV.MAVLINK_MSG_ID_VFR_HUD, MAV.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
          MAV.MAVLINK_MSG_ID_RC_CHANNELS, MAV.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, *_STREAMED}
GCS_TICK = 1.0 / 400.0  # GCS::update_receive in Rover's scheduler table


def _safe_sqrt(v: float) -> float:
    """AP_Math ``safe_sqrt``: 0 where the root is NaN (a NaN, or inf - inf, in the sum of squares)."""
    r = math.sqrt(v) if v >= 0 else math.nan
    return 0.0 if math.isnan(r) else r


def _constrain(v: float, low: float, high: float, nan: float) -> float:
    """AP_Math ``constrain_float``: a NaN becomes the middle of the range it is constrained to (and an internal
    error); +-inf become the bounds. ``nan``: that middle, as the caller's range has it."""
    return nan if math.isnan(v) else max(low, min(high, v))


class MavlinkRover(SigningMixin, LinkMixin, ThreadedDevice):
    """See the module docstring. Listens on ``host:port`` (0: a free port, read ``.port`` after ``start()``)."""

    thread_name = "mavlink-rover"

    def __init__(self, vehicle: SimVehicle, host: str = "127.0.0.1", port: int = 0, *, transport: str = "udp",
                 sysid: int = 1, compid: int = 1, wp_speed: float = 2.0, str_rat_max: float = 2.0,
                 guid_timeout: float = 3.0, init_s: float = 0.3, ekf_position_s: float = 1.0,
                 ekf_origin_s: float | None = None, initial_mode: str = "MANUAL",
                 params: dict[str, float] | None = None, decel_max: float = 2.0, coast_decel: float = 0.3,
                 signing_key: bytes | None = None, signing_store: str | os.PathLike[str] | None = None,
                 signing_save_s: float = SIGNING_SAVE_S) -> None:
        super().__init__()
        if transport not in ("udp", "tcp"):
            raise ValueError(f"transport {transport!r}: udp or tcp")
        self.vehicle = vehicle
        self.host, self.port, self.transport = host, int(port), transport
        self.sysid, self.compid = int(sysid), int(compid)
        self.wp_speed, self.str_rat_max, self.guid_timeout = float(wp_speed), float(str_rat_max), float(guid_timeout)
        self.init_s, self.ekf_position_s = float(init_s), float(ekf_position_s)
        self.ekf_origin_s = self.ekf_position_s if ekf_origin_s is None else float(ekf_origin_s)
        self.initial_mode = MODES[initial_mode]
        self.custom_mode = INITIALISING
        self.armed = False
        self.safety_switch = False  # True: the hardware safety switch is still on, arming refused
        # what it models is readable under Rover's names (a ground station reads the learner's range from them)
        modelled = {"WP_SPEED": float(wp_speed), "ATC_STR_RAT_MAX": math.degrees(float(str_rat_max)),
                    "ATC_DECEL_MAX": float(decel_max)}
        self.params: dict[str, float] = {**PARAM_DEFAULTS, **modelled, **(params or {})}
        self.decel_max, self.coast_decel = float(decel_max), float(coast_decel)
        self.slowing_at: float | None = None  # the body slows down by itself since then (braking or coasting)
        self.disarms: list[tuple[float, float]] = []  # (time, body speed) of every disarm, for tests
        self.gcs_seen = -math.inf  # the last HEARTBEAT of the ground station (SYSID_MYGCS)
        self.failsafe_since: float | None = None  # the GCS failsafe condition holds since then
        self.failsafe_taken = False
        self.intervals: dict[int, float] = dict(_STREAMED)  # message id -> period (s); inf: stopped
        self.target: tuple[float, float] | None = None  # GUIDED turn rate and speed target (ENU v, omega)
        self.target_time = -math.inf
        # what happened, for tests (bounded)
        self.setpoints: list[dict[str, Any]] = []  # accepted SET_POSITION_TARGET_LOCAL_NED, last 200
        self.ignored_setpoints: dict[str, int] = {}  # reason -> count (ArduPilot ignores them silently)
        self.commands: list[dict[str, Any]] = []  # every command handled, last 500: t, name, params, result
        self.statustexts: list[str] = []  # every STATUSTEXT sent, last 200
        self.bad = 0  # bytes that did not parse
        self.internal_errors: dict[str, int] = {}  # AP_InternalError flags raised (a NaN constrained)
        self.dropped_on_disconnect = 0  # tcp: bytes never parsed because their sender had gone
        self.blackout = False
        self._texts: list[tuple[int, str]] = []  # queued for the next send phase (after the ACKs)
        self._calls: queue.SimpleQueue[tuple[Callable[[], Any], threading.Event, list[Any]]] = queue.SimpleQueue()
        self._tx_lock = threading.Lock()
        self._rx = bytearray()
        self._sock: socket.socket | None = None  # udp socket, or tcp listening socket
        self._client: socket.socket | None = None  # tcp client
        self._peer: tuple[str, int] | None = None  # udp peer
        self._initialised = False
        self._due: dict[Any, float] = {"hb": 0.0, **{mid: 0.0 for mid in _STREAMED}}
        self.mav = MAV.MAVLink(Tx(self), srcSystem=self.sysid, srcComponent=self.compid)
        self.mav.robust_parsing = True
        self._parser = MAV.MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid)
        self._parser.robust_parsing = True
        self._init_signing(signing_key, signing_store, signing_save_s)
        self.t0 = time.monotonic()
        self.fence = EmulatedFence(self, HOLD)  # the geofence (sim_learner/mavlink_fence.py)

    # ---------------------------------------------------------------------------------------- operator side
    def _call(self, fn: Callable[[], Any], timeout: float = 2.0) -> Any:
        """Run ``fn`` on the rover's thread (state belongs to it) and return its result."""
        if self._thread is None or not self._thread.is_alive():
            return fn()
        done, out = threading.Event(), []
        self._calls.put((fn, done, out))
        if not done.wait(timeout):
            raise TimeoutError("the rover thread did not run the call")
        return out[0]

    def rc_mode_switch(self, mode: str) -> bool:
        """The transmitter's mode switch (``Rover::set_mode(..., RC_COMMAND)``); False if the vehicle refused."""
        return self._call(lambda: self._set_mode(MODES[mode], time.monotonic()))

    def rc_arm(self, armed: bool = True) -> bool:
        """The transmitter's arming switch (with the pre-arm checks); False if refused."""
        return self._call(lambda: self._arm(armed, time.monotonic()) == MAV.MAV_RESULT_ACCEPTED)

    def radio_blackout(self, on: bool) -> None:
        """Out of radio range: nothing in, nothing out (the vehicle itself runs on)."""
        self.blackout = bool(on)

    def foreign(self, sysid: int, compid: int = 1) -> Any:
        """A pymavlink encoder sending as another system on this link (a second vehicle, another ground station)."""
        m = MAV.MAVLink(Tx(self), srcSystem=int(sysid), srcComponent=int(compid))
        return m

    def text(self, text: str, severity: int = MAV.MAV_SEVERITY_WARNING) -> None:
        """Queue a STATUSTEXT as the autopilot would (sent at its next send phase)."""
        self._call(lambda: self._text(text, severity))

    # ------------------------------------------------------------------------------------------- state
    @property
    def mode_name(self) -> str:
        return MODE_NAMES.get(self.custom_mode, str(self.custom_mode))

    def has_position(self, now: float) -> bool:
        return self._initialised and now - self.t0 >= self.ekf_position_s

    def has_origin(self, now: float) -> bool:
        return self._initialised and now - self.t0 >= self.ekf_origin_s

    def _text(self, text: str, severity: int = MAV.MAV_SEVERITY_WARNING) -> None:
        self._texts.append((severity, text[:50]))
        del self._texts[:-32]  # ArduPilot's text queue is bounded too
        self.statustexts.append(text)
        del self.statustexts[:-200]

    def _set_mode(self, mode: int, now: float) -> bool:
        """``Rover::set_mode``: False (with its STATUSTEXT) if refused."""
        if mode not in ROVER_MODES:
            self._text(f"No such mode {mode}")
            return False
        if mode == self.custom_mode:
            return True
        if self.armed and mode in NEEDS_POSITION and not self.has_position(now):
            self._text("Flight mode change failed")
            return False
        self.custom_mode = mode
        self.target = None  # leaving or entering GUIDED: no target (GUIDED starts in its Stop submode)
        self._slow_down(now)
        self._heartbeat()  # gcs().send_message(MSG_HEARTBEAT) on every change
        return True

    def _prearm_failure(self, now: float) -> str | None:
        if self.safety_switch:
            return "Hardware safety switch"
        if self.custom_mode == INITIALISING:
            return "Mode not armable"
        if self.custom_mode in NEEDS_POSITION and not self.has_position(now):
            return "Need Position Estimate"
        return None

    def _arm(self, arm: bool, now: float) -> int:
        if arm == self.armed:
            return MAV.MAV_RESULT_ACCEPTED
        if arm:
            failure = self._prearm_failure(now)
            if failure is not None:
                self._text(f"PreArm: {failure}", MAV.MAV_SEVERITY_CRITICAL)
                return MAV.MAV_RESULT_FAILED
            self.armed = True
            self._text("Throttle armed", MAV.MAV_SEVERITY_INFO)
            self._drive(now)
        else:
            self.armed = False
            self.disarms.append((now, self.vehicle.advance(now).v))  # the body's speed as the motors went off
            self._slow_down(now)  # coasting
            self._text("Throttle disarmed", MAV.MAV_SEVERITY_INFO)
        return MAV.MAV_RESULT_ACCEPTED

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        if msg_id not in _KNOWN:
            return MAV.MAV_RESULT_FAILED
        if interval_us == 0:
            period = _STREAMED.get(msg_id, 1.0)
        elif interval_us == -1:
            period = math.inf
        else:
            period = min(max(interval_us, 1000.0), 60e6) / 1e6
        if msg_id in self.intervals:
            self.intervals[msg_id] = period
            self._due[msg_id] = time.monotonic()  # the new interval applies from now
        return MAV.MAV_RESULT_ACCEPTED

    # ------------------------------------------------------------------------------------------- messages
    def _for_us(self, msg: Any) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (0, self.compid)

    def _handle(self, msg: Any, now: float) -> None:
        t = msg.get_type()
        if t == "BAD_DATA":
            self.bad += 1
            return
        if t in ("COMMAND_LONG", "COMMAND_INT"):
            if not self._for_us(msg):
                return
            if t == "COMMAND_LONG":
                p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            else:
                p = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
            result = self._command(int(msg.command), p, now)
            self.commands.append({"t": now, "command": int(msg.command), "params": p, "result": result,
                                  "from": (msg.get_srcSystem(), msg.get_srcComponent())})
            del self.commands[:-500]
            self.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        elif t == "SET_POSITION_TARGET_LOCAL_NED" and self._for_us(msg):
            self._setpoint(msg, now)
        elif t == "HEARTBEAT" and msg.get_srcSystem() == int(self.params["SYSID_MYGCS"]):
            self.gcs_seen = now
        elif t == "PARAM_REQUEST_READ" and self._for_us(msg):
            names = list(self.params)
            name = msg.param_id.rstrip("\x00") if msg.param_index < 0 else (
                names[msg.param_index] if 0 <= msg.param_index < len(names) else None)
            if name in self.params:
                self._param_value(name)
        elif t == "PARAM_REQUEST_LIST" and self._for_us(msg):
            for name in self.params:
                self._param_value(name)
        elif t in ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "PARAM_SET") and self._for_us(msg):
            self.fence.handle(msg, now)

    def _command(self, command: int, p: tuple[float, ...], now: float) -> int:
        used = {MAV.MAV_CMD_DO_SET_MODE: 2, MAV.MAV_CMD_COMPONENT_ARM_DISARM: 1, MAV.MAV_CMD_SET_MESSAGE_INTERVAL: 2}
        if not all(math.isfinite(float(v)) for v in p[: used.get(command, 0)]):
            return MAV.MAV_RESULT_DENIED  # a NaN/inf parameter is no mode, message id or arming request
        if command == MAV.MAV_CMD_DO_SET_MODE:
            if not int(p[0]) & MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return MAV.MAV_RESULT_DENIED
            return MAV.MAV_RESULT_ACCEPTED if self._set_mode(int(p[1]), now) else MAV.MAV_RESULT_FAILED
        if command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                return self._arm(True, now)
            if p[0] == 0.0:
                return self._arm(False, now)
            return MAV.MAV_RESULT_UNSUPPORTED
        if command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(int(p[0]), float(p[1]))
        fenced = self.fence.command(command, p, now)
        return MAV.MAV_RESULT_UNSUPPORTED if fenced is None else fenced

    def _param_value(self, name: str) -> None:
        names = list(self.params)
        self.mav.param_value_send(name.encode(), float(self.params[name]), MAV.MAV_PARAM_TYPE_REAL32, len(names),
                                  names.index(name))

    def _gcs_failsafe(self, now: float) -> None:
        """Rover's GCS failsafe (see the module docstring)."""
        p = self.params
        lost = bool(p["FS_GCS_ENABLE"]) and math.isfinite(self.gcs_seen) and now - self.gcs_seen > p["FS_GCS_TIMEOUT"]
        if not lost:
            self.failsafe_since, self.failsafe_taken = None, False
            return
        if self.failsafe_since is None:
            self.failsafe_since = now
        if self.failsafe_taken or not self.armed or now - self.failsafe_since <= p["FS_TIMEOUT"]:
            return
        self.failsafe_taken = True
        self._text("Failsafe: GCS", MAV.MAV_SEVERITY_CRITICAL)
        if int(p["FS_ACTION"]) in (1, 2, 3, 4):  # RTL / SmartRTL are not modelled: Hold, their own fallback
            self._set_mode(HOLD, now)
            self.vehicle.stop(now)

    @property
    def bad_signatures(self) -> int:
        """Messages refused by signing (unsigned, forged or replayed)."""
        s = self._parser.signing
        return s.badsig_count + s.reject_count

    def _ignore(self, reason: str) -> None:
        self.ignored_setpoints[reason] = self.ignored_setpoints.get(reason, 0) + 1

    def _setpoint(self, msg: Any, now: float) -> None:
        if self.custom_mode != GUIDED:
            return self._ignore("not GUIDED")
        if not self.has_origin(now):
            return self._ignore("no EKF origin")
        if msg.coordinate_frame not in _FRAMES:
            return self._ignore("frame")
        mask = msg.type_mask
        pos_ignore, vel_ignore, acc_ignore = mask & _POS_IGNORE, mask & _VEL_IGNORE, mask & _ACC_IGNORE
        yaw_ignore, yaw_rate_ignore = mask & _YAW_IGNORE, mask & _YAW_RATE_IGNORE
        speed = 0.0
        if not vel_ignore:
            speed = min(_safe_sqrt(msg.vx * msg.vx + msg.vy * msg.vy), self.wp_speed)
            if (not yaw_ignore or not yaw_rate_ignore) and msg.vx < 0:
                speed = -speed
        rate = 0.0
        if not yaw_rate_ignore:
            previous = -self.target[1] if self.target is not None else 0.0
            rate = _constrain(msg.yaw_rate, -self.str_rat_max, self.str_rat_max, nan=previous)
            if math.isnan(msg.yaw_rate):
                self.internal_errors["constraining_nan"] = self.internal_errors.get("constraining_nan", 0) + 1
        if not pos_ignore or not acc_ignore or not yaw_ignore or (vel_ignore and yaw_rate_ignore):
            return self._ignore("unsupported type_mask")  # position / heading targets: not modelled here
        self.target, self.target_time = (speed, -rate), now  # NED clockwise -> ENU counter-clockwise
        self.setpoints.append({"t": now, "vx": msg.vx, "vy": msg.vy, "yaw_rate": msg.yaw_rate,
                               "frame": msg.coordinate_frame, "type_mask": msg.type_mask, "armed": self.armed})
        del self.setpoints[:-200]
        self._drive(now)

    def _drive(self, now: float) -> None:
        if self.target is None or not self.armed or self.target == (0.0, 0.0):
            self._slow_down(now)
        else:
            self.slowing_at = None
            self.vehicle.command(self.target[0], self.target[1], now)

    def _slow_down(self, now: float) -> None:
        """Brake (armed) or coast (disarmed) toward a stop, from the body's speed now (see the module docstring)."""
        st = self.vehicle.advance(now)
        rate = self.decel_max if self.armed else self.coast_decel
        if self.slowing_at is not None:
            dv = rate * (now - self.slowing_at)
            v = math.copysign(max(0.0, abs(st.v) - dv), st.v)
        else:
            v = st.v
        if abs(v) < 1e-3 or rate <= 0.0:
            self.slowing_at = None
            self.vehicle.stop(now)
            return
        self.slowing_at = now
        self.vehicle.roll(v, 0.0, now)

    # ------------------------------------------------------------------------------------------- output
    def _heartbeat(self) -> None:
        base = MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.custom_mode in AUTOPILOT_MODES:
            base |= MAV.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.custom_mode in MANUAL_INPUT_MODES:
            base |= MAV.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if self.armed and self.custom_mode != INITIALISING:
            base |= MAV.MAV_MODE_FLAG_SAFETY_ARMED
        status = (MAV.MAV_STATE_CALIBRATING if self.custom_mode == INITIALISING else
                  MAV.MAV_STATE_STANDBY if self.custom_mode == HOLD else MAV.MAV_STATE_ACTIVE)
        self.mav.heartbeat_send(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, base, self.custom_mode,
                                status)

    def _run(self) -> None:
        due = self._due
        while not self._stop.is_set():
            now = time.monotonic()
            if self._rx:  # bytes wait for the next scheduler tick on the 400 Hz grid
                wake = self.t0 + (math.floor((now - self.t0) / GCS_TICK) + 1) * GCS_TICK
            else:
                wake = min(due.values()) if self.connected else now + 0.05
            wake = min(wake, self._next_event())  # boot and GUID_TIMEOUT run on the vehicle's clock, not ours
            try:
                select.select(self._fds(), [], [], min(max(0.0, wake - now), 0.05))
            except (OSError, ValueError):
                time.sleep(0.001)
            self._drain()  # the UART timer runs whenever bytes arrive (and notices EOF at once)
            while True:
                try:
                    fn, done, out = self._calls.get_nowait()
                except queue.Empty:
                    break
                out.append(fn())
                done.set()
            now = time.monotonic()
            if now < wake:
                continue
            self._update(now)
            if self._rx and self.connected:  # GCS::update_receive
                data, self._rx = bytes(self._rx), bytearray()
                try:
                    msgs = self._parser.parse_buffer(data) or []
                except Exception:  # pymavlink can raise on some malformed frames even when robust
                    self.bad += 1
                    msgs = []
                for msg in msgs:
                    self._handle(msg, now)
            if not self.connected:
                continue
            if now >= due["hb"]:
                self._save_signing_timestamp(now)  # send_message(MSG_HEARTBEAT): save_signing_timestamp(false)
                self._heartbeat()
                due["hb"] = now + 1.0
            self._telemetry(now, due)
            for severity, text in self._texts:  # GCS::service_statustext, after this tick's ACKs
                self.mav.statustext_send(severity, text.encode())
            self._texts.clear()

    def _next_event(self) -> float:
        """When :meth:`_update` has something to do next: the end of boot, a GUIDED target's timeout."""
        events = [math.inf, self.fence.next_check(), self._gps_due()]
        if not self._initialised:
            events.append(self.t0 + self.init_s)
        if self.target is not None:
            events.append(self.target_time + self.guid_timeout)
        if self.slowing_at is not None:
            events.append(self.slowing_at + 0.02)
        if self.params["FS_GCS_ENABLE"] and self.armed and not self.failsafe_taken:  # the GCS failsafe's next step
            events.append(self.gcs_seen + self.params["FS_GCS_TIMEOUT"] + 1e-3 if self.failsafe_since is None
                          else self.failsafe_since + self.params["FS_TIMEOUT"] + 1e-3)
        return min(events)

    def _update(self, now: float) -> None:
        self._gcs_failsafe(now)
        self.fence.check(now)
        self._gps_update(now)
        if not self._initialised and now - self.t0 >= self.init_s:
            self._initialised = True
            self.custom_mode = INITIALISING
            self._set_mode(self.initial_mode, now)  # INITIAL_MODE, whatever was set during boot
        if self.target is not None and now - self.target_time > self.guid_timeout:
            self.target = None
            self._text(f"target not received last {self.guid_timeout:g}secs, stopping")  # SITL: "last 3secs"
            self._slow_down(now)
        elif self.slowing_at is not None:
            self._slow_down(now)

    def _telemetry(self, now: float, due: dict[Any, float]) -> None:
        lpn, att = MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, MAV.MAVLINK_MSG_ID_ATTITUDE
        if now < due[lpn] and now < due[att]:
            return
        x, y, th = self.vehicle.measured_pose(now)
        st = self.vehicle.state
        boot_ms = int((now - self.t0) * 1000) & 0xFFFFFFFF
        if now >= due[lpn]:
            if self.has_origin(now):  # send_local_position: nothing without an origin
                # ENU (x east, y north) -> NED (x north, y east); the body speed projected on the axes
                self.mav.local_position_ned_send(boot_ms, y, x, 0.0, st.v * math.sin(th), st.v * math.cos(th), 0.0)
            due[lpn] = now + self.intervals[lpn] if math.isfinite(self.intervals[lpn]) else now + 0.5
        if now >= due[att]:
            if math.isfinite(self.intervals[att]):
                yaw = math.remainder(math.pi / 2 - th, 2 * math.pi)
                self.mav.attitude_send(boot_ms, 0.0, 0.0, yaw, 0.0, 0.0, -st.omega)
            due[att] = now + self.intervals[att] if math.isfinite(self.intervals[att]) else now + 0.5
