"""pymavlink's ardupilotmega dialect (MAVLink 2) and the Rover's mode numbers, loaded when the first driver is built:
reading a driver host's configuration, which holds every link's section, must not import pymavlink."""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Any

from drivers.mavlink.state import RoverModes


@dataclass(frozen=True, slots=True)
class Dialect:
    """What the link uses of pymavlink: the module, the ardupilotmega definitions, the Rover's modes and the
    component id we speak as (a ground control station)."""

    mavutil: Any
    mav: Any  # mavutil.mavlink: message ids, enums, MAV_CMD_*, MAV_RESULT_*
    modes: RoverModes
    source_component: int


@functools.cache
def load_pymavlink() -> Dialect:
    """Import pymavlink (once) with MAVLink 2 and the ardupilotmega dialect."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    mavutil.set_dialect("ardupilotmega")
    mav = mavutil.mavlink
    by_name = mavutil.mode_mapping_byname(mav.MAV_TYPE_GROUND_ROVER)
    modes = RoverModes(guided=by_name["GUIDED"], initialising=by_name["INITIALISING"],
                       names=dict(mavutil.mode_mapping_bynumber(mav.MAV_TYPE_GROUND_ROVER)))
    return Dialect(mavutil=mavutil, mav=mav, modes=modes, source_component=mav.MAV_COMP_ID_MISSIONPLANNER)


def mode_name(custom_mode: int | None) -> str:
    """Rover's name for a custom mode number (``"HOLD"``), ``"unknown"`` before the first HEARTBEAT."""
    if custom_mode is None:
        return "unknown"
    return load_pymavlink().modes.name(custom_mode)
