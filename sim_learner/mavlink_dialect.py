"""pymavlink's ardupilotmega definitions in MAVLink 2 for the emulated rover and the SITL ground station, with no
change to the process when imported.

``MAV`` is the MAVLink 2 ardupilotmega module itself (what ``mavutil.set_dialect("ardupilotmega")`` picks with
``MAVLINK20`` set), imported directly: building frames and parsers with it needs neither. A pymavlink *connection*
(``mavutil.mavlink_connection``) builds its parser from mavutil's process-wide dialect, which is chosen from the
environment, so :func:`mavutil_v2` makes that choice (once, when the first connection is to be made): importing an
emulator or a test helper must not change a process's environment or its pymavlink (docs/ARCHITECTURE.md, section 2).
"""

from __future__ import annotations

import functools
import os
from types import ModuleType

from pymavlink.dialects.v20 import ardupilotmega as MAV


@functools.cache
def mavutil_v2() -> ModuleType:
    """pymavlink's ``mavutil`` speaking MAVLink 2 with the ardupilotmega dialect (sets ``MAVLINK20`` unless the
    process set it): call it before making a connection, never at import."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    mavutil.set_dialect("ardupilotmega")
    return mavutil


__all__ = ["MAV", "mavutil_v2"]
