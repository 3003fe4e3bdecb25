"""``[link.mavlink]``: the MAVLink link's configuration (read without importing pymavlink)."""

from __future__ import annotations

from typing import Annotated

from bridge.core.config import Cfg, Rule, meta


class MavlinkLinkConfig(Cfg):
    """``[link.mavlink]``: an ArduPilot Rover in GUIDED mode."""

    url: Annotated[str, meta("pymavlink connection: tcp:HOST:5760 (SITL), udpout:HOST:PORT, /dev/ttyUSB0",
                             min_length=1)] = (
        "udpout:127.0.0.1:14550")
    baud: Annotated[int, meta("serial baud rate", ge=1200, le=4_000_000)] = 57600
    target_system: Annotated[int, meta("the vehicle's MAVLink system id", ge=1, le=255)] = 1
    target_component: Annotated[int, meta("the autopilot's component id", ge=0, le=255)] = 1
    source_system: Annotated[int, meta(
        "our system id: 255 a ground control station (QGroundControl's and MAVProxy's own: give another beside one); "
        "a companion computer takes the vehicle's own system id", ge=1, le=255)] = 255
    source_component: Annotated[int, meta(
        "our component id: 190 a ground control station (MAV_COMP_ID_MISSIONPLANNER), 191 a companion computer "
        "(MAV_COMP_ID_ONBOARD_COMPUTER), the ids that share a radio with a ground station without colliding",
        ge=1, le=255)] = 190
    rate_hz: Annotated[float, meta("LOCAL_POSITION_NED and ATTITUDE rate requested, Hz", gt=0.0, le=100.0)] = 20.0
    clock_window_s: Annotated[float, meta("window of the vehicle-clock offset estimate that stamps poses at their "
                                          "time_boot_ms, s", gt=0.0, le=600.0)] = 5.0
    setpoint_rate_hz: Annotated[float, meta(
        "set-points repeating an unchanged command, Hz (a changed command and a stop go at once; 50 Hz set-points fill "
        "56 % of a 57600-baud radio)", gt=0.0, le=50.0)] = 10.0
    max_setpoint_hz: Annotated[float, meta(
        "the most set-points per second, changed commands included (a 57600-baud radio carries ~90 a second and "
        "nothing else then); a stop after motion always goes at once", gt=0.0, le=200.0)] = 25.0
    open_timeout: Annotated[float, meta("s for heartbeat, EKF position, GUIDED and arming", gt=0.0, le=300.0)] = 30.0
    heartbeat_timeout: Annotated[float, meta("s without the vehicle's 1 Hz HEARTBEAT before the link counts as down",
                                             ge=1.5, le=60.0)] = 3.0
    position_timeout: Annotated[float, meta("s without LOCAL_POSITION_NED before the vehicle counts as not ready "
                                            "(ArduPilot sends none without an EKF origin)", gt=0.0, le=60.0)] = 1.0
    ack_timeout: Annotated[float, meta("s to wait for each COMMAND_ACK before sending the command again", gt=0.0,
                                       le=30.0)] = 1.0
    command_retries: Annotated[int, meta("times a command without COMMAND_ACK is sent again", ge=0, le=10)] = 3
    close_timeout: Annotated[float, meta("s close() waits for the disarm to be acknowledged", gt=0.0, le=60.0)] = 3.0
    reconnect_max_s: Annotated[float, meta("longest wait between attempts to re-open a failed connection, s (the "
                                           "wait doubles from 0.25 s)", ge=0.25, le=300.0)] = 5.0
    statustext_keep: Annotated[int, meta("the vehicle's last STATUSTEXTs kept for health() and error texts", ge=1,
                                         le=100)] = 8
    disarm_on_close: Annotated[bool, meta("disarm when the driver host stops (only a vehicle still in GUIDED)")] = True
    signing_key_file: Annotated[str, meta(
        "MAVLink 2 signing key (scmbridge keys mavlink; the autopilot gets the same key with SETUP_SIGNING): every "
        "message we send is signed and unsigned or badly signed ones are refused; empty: no signing")] = ""
    heartbeat_hz: Annotated[float, meta(
        "our HEARTBEATs per second: what ArduPilot's GCS failsafe watches (FS_GCS_ENABLE with MAV_GCS_SYSID our "
        "source_system); faster lets a shorter FS_GCS_TIMEOUT hold a rover whose host died (docs/SECURITY.md)",
        ge=1.0, le=20.0)] = 1.0

    def unauthenticated(self) -> str:
        """Why anyone on the link can command the vehicle ("" when MAVLink 2 signing is on): the driver host's status
        and ``scmbridge doctor`` say it (drivers.base.link_unauthenticated)."""
        return "" if self.signing_key_file else "MAVLink signing is off (no signing_key_file)"

    @property
    def companion(self) -> bool:
        """We speak as a component of the vehicle itself (its own system id): a companion computer's HEARTBEAT
        (MAV_TYPE_ONBOARD_CONTROLLER), not a ground station's; ArduPilot's GCS failsafe then watches the ground
        station's heartbeat (MAV_GCS_SYSID / SYSID_MYGCS), not ours (docs/OPERATING.md, "First day with your
        rover")."""
        return self.source_system == self.target_system

    def __post_init__(self) -> None:
        if (self.source_system, self.source_component) == (self.target_system, self.target_component):
            raise Rule(f"source_system/source_component {self.source_system}/{self.source_component} are the "
                       "autopilot's own ids: the vehicle drops what seems to come from itself; a companion computer "
                       "is component 191")
        if self.position_timeout < 2.0 / self.rate_hz:
            raise Rule(f"position_timeout = {self.position_timeout} s is shorter than two LOCAL_POSITION_NED "
                             f"periods at rate_hz = {self.rate_hz}")

