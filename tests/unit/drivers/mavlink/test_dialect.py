"""drivers/mavlink/dialect.py: pymavlink loaded once, MAVLink 2 with the ardupilotmega dialect, and Rover's mode
names. (tests/unit/drivers/mavlink/test_state.py checks GUIDED/INITIALISING numbers and one name.)"""

from __future__ import annotations

import subprocess
import sys

from drivers.mavlink.dialect import Dialect, load_pymavlink, mode_name


def test_pymavlink_is_loaded_once_as_one_dialect() -> None:
    d = load_pymavlink()
    assert isinstance(d, Dialect) and load_pymavlink() is d
    assert d.mav is d.mavutil.mavlink
    assert d.source_component == d.mav.MAV_COMP_ID_MISSIONPLANNER  # we speak as a ground control station


def test_the_dialect_is_ardupilotmega_over_mavlink_2() -> None:
    d = load_pymavlink()
    assert d.mav.WIRE_PROTOCOL_VERSION == "2.0"
    assert hasattr(d.mav, "MAVLink_ekf_status_report_message")  # an ardupilotmega message, not in common
    assert d.mavutil.current_dialect == "ardupilotmega"


def test_rovers_modes_by_number() -> None:
    modes = load_pymavlink().modes
    assert modes.names[modes.guided] == "GUIDED" and modes.names[modes.initialising] == "INITIALISING"
    assert (mode_name(0), mode_name(4), mode_name(15)) == ("MANUAL", "HOLD", "GUIDED")
    assert mode_name(None) == "unknown" and mode_name(250) == "mode 250"


def test_a_process_without_mavlink20_set_still_speaks_mavlink_2() -> None:
    code = ("import os; os.environ.pop('MAVLINK20', None); from drivers.mavlink.dialect import load_pymavlink; "
            "assert load_pymavlink().mav.WIRE_PROTOCOL_VERSION == '2.0'; assert os.environ['MAVLINK20'] == '1'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
