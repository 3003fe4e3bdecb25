"""sim_learner/mavlink_dialect.py: the MAVLink 2 ardupilotmega definitions without a change to the process, and
pymavlink's connections switched to them only when asked (in a fresh interpreter: the switch is process-wide)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def test_the_definitions_are_mavlink2_and_frame_a_signed_heartbeat() -> None:
    from sim_learner.mavlink_dialect import MAV

    assert MAV.WIRE_PROTOCOL_VERSION == "2.0"

    class Out:
        frames: list[bytes] = []

        def write(self, b: bytes) -> None:
            self.frames.append(bytes(b))

    out = Out()
    mav = MAV.MAVLink(out, srcSystem=1, srcComponent=1)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = bytes(32), True, 1
    mav.heartbeat_send(MAV.MAV_TYPE_GROUND_ROVER, MAV.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0)
    assert out.frames[0][0] == 0xFD and out.frames[0][2] & 0x01  # MAVLink 2's magic, the signed flag


def test_importing_changes_nothing_and_mavutil_v2_switches_connections_to_mavlink2() -> None:
    code = ("import os\nimport pymavlink.mavutil as mu\nbefore = (os.environ.get('MAVLINK20'), "
            "mu.mavlink.WIRE_PROTOCOL_VERSION)\nfrom sim_learner import mavlink_dialect as d\n"
            "mid = (os.environ.get('MAVLINK20'), mu.mavlink.WIRE_PROTOCOL_VERSION)\n"
            "assert d.mavutil_v2() is mu\nafter = (os.environ.get('MAVLINK20'), mu.mavlink.WIRE_PROTOCOL_VERSION, "
            "mu.mavlink is d.MAV)\nprint(before, mid, after)\n")
    env = {k: v for k, v in os.environ.items() if k != "MAVLINK20"}
    env["PYTHONPATH"] = str(ROOT)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "(None, '1.0') (None, '1.0') ('1', '2.0', True)"
