"""CAN link: a differential-drive base with one ODrive motor controller (firmware 0.6, CANSimple) per wheel.

Cut by job: :mod:`.config` (``[link.can]``), :mod:`.codec` (CANSimple frames from the shipped DBC, pure),
:mod:`.odometry` (encoder estimates -> pose with the plausibility checks, pure), :mod:`.axis` (the two controllers as a
state machine: Heartbeats, latched faults, arming, the verdict; pure) and :mod:`.driver` (:class:`CanDriver`: the bus
supervisor wiring them). Enumerations and error names are in
:mod:`drivers.odrive`. python-can and cantools are imported when a driver is built or a frame coded, not with the
package: the configuration needs neither.
"""

from __future__ import annotations

from drivers.can.codec import database, decode, encode
from drivers.can.config import CanLinkConfig
from drivers.can.driver import AxisHealth, CanCounters, CanDriver, CanHealthDetail

#: the link's plugin entry (``drivers.LINKS``): its ``[link.can]`` section, its driver, and whether ``scmbridge
#: learner`` emulates it (the two ODrive controllers, :mod:`sim_learner.can_ecu`)
CONFIG = CanLinkConfig
DRIVER = CanDriver
EMULATED = True

__all__ = ["CONFIG", "DRIVER", "EMULATED", "AxisHealth", "CanCounters", "CanDriver", "CanHealthDetail",
           "CanLinkConfig", "database", "decode", "encode"]
