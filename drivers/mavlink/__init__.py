"""MAVLink link: an ArduPilot Rover in GUIDED mode (pymavlink, MAVLink 2, ardupilotmega).

Cut by job: :mod:`.config` (``[link.mavlink]``), :mod:`.client` (the connection and the COMMAND_LONG / COMMAND_ACK
protocol), :mod:`.state` (what the vehicle said and the pure decisions on it: whether it accepts set-points,
what a change of that means, when a set-point goes out, the failsafe report), :mod:`.pose` (ENU poses from its
telemetry, pure) and :mod:`.driver` (:class:`MavlinkDriver`, wiring them). pymavlink is imported when the first
driver is built (:func:`load_pymavlink`), not with the package: reading the configuration does not need it.
"""

from __future__ import annotations

from drivers.mavlink.client import NO_ACK, result_name
from drivers.mavlink.config import MavlinkLinkConfig
from drivers.mavlink.dialect import load_pymavlink, mode_name
from drivers.mavlink.driver import TYPE_MASK_VEL_YAWRATE, MavlinkDriver, MavlinkHealthDetail
from drivers.mavlink.pose import (
    ATTITUDE_MAX_LAG,
    POSITION_MAX,
    SPEED_MAX,
    YAW_MAX,
    YAW_RATE_MAX,
    telemetry_valid,
)
from drivers.mavlink.state import FAILSAFE_PARAMS, GUIDED_TIMEOUT_S

#: the link's plugin entry (``drivers.LINKS``): its ``[link.mavlink]`` section, its driver, and whether ``scmbridge
#: learner`` emulates it (an ArduPilot-Rover-like vehicle, :mod:`sim_learner.mavlink_rover`)
CONFIG = MavlinkLinkConfig
DRIVER = MavlinkDriver
EMULATED = True

__all__ = ["ATTITUDE_MAX_LAG", "CONFIG", "DRIVER", "EMULATED", "FAILSAFE_PARAMS", "GUIDED_TIMEOUT_S", "NO_ACK",
           "POSITION_MAX", "SPEED_MAX", "TYPE_MASK_VEL_YAWRATE", "YAW_MAX", "YAW_RATE_MAX", "MavlinkDriver",
           "MavlinkHealthDetail", "MavlinkLinkConfig", "load_pymavlink", "mode_name", "result_name",
           "telemetry_valid"]
