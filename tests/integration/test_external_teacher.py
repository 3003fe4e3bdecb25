"""A lab's own teacher, end to end over real Zenoh: the shipped example external teacher (its own process, using
only the wire schema) drives the emulated CAN learner through a transfer-only station and a driver host."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children
from tests.collect import Collector

ROOT = Path(__file__).resolve().parents[2]
#: the methods of a command the learned pairs mapped (an SC region, or linear along a learned limit or on a triangle)
MAPPED = {"scm", "barycentric"}
MISSION = ROOT / "bridge" / "missions" / "paper_s_path.toml"


@pytest.mark.slow
@pytest.mark.timeout(150)
def test_the_example_external_teacher_drives_the_robot_through_the_transfer_service(tmp_path) -> None:
    port, robot = free_port(), f"ext{os.getpid()}"
    mission = load_mission(MISSION)
    x0 = ",".join(f"{a:.6f}" for a in mission.start)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    cfg = tmp_path / "station.toml"
    cfg.write_text('[teacher]\nkind = "external"\n')
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        k, col = M.Keys(robot), Collector(session)
        lock = col.lock
        got = {"state": col.listen(k.state, M.LearnerState), "cmd": col.listen(k.cmd, M.Command),
               "limits": col.listen(k.limits, M.Limits),
               "status": col.listen(M.status_key(robot, "station"), M.Status)}
        kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, *client, "--duration", "140"])
        kids.spawn(["station", "--start", "--config", str(cfg), *client, "--store", str(tmp_path / "p.bin"),
                    "--duration", "130"])
        said = open(tmp_path / "teacher.out", "w")  # noqa: SIM115 (closed with the process, below)
        teacher = subprocess.Popen([sys.executable, str(ROOT / "deploy" / "examples" / "external_teacher.py"),
                                    "--robot", robot, "--mode", "client", "--connect", tcp(port), "--mission",
                                    str(MISSION), "--duration", "120"], start_new_session=True, stdout=said)
        kids.procs.append(teacher)
        t_end = time.monotonic() + 110
        progress = 0.0
        while time.monotonic() < t_end:
            time.sleep(0.5)  # the poll step: until the robot is far enough along (the loop's deadline is the test)
            with lock:
                last = got["state"][-1] if got["state"] else None
            if last is not None:
                progress = max(progress, mission.progress([last.x, last.y]))
            with lock:
                mapped = any(c.method in MAPPED for c in got["cmd"])
            if progress > 0.25 and mapped:  # how soon the first SC region forms depends on the machine's load
                break
        children = kids.said()  # the driver host's and the station's last lines, for a failure's message
    said.close()
    out = (tmp_path / "teacher.out").read_text()
    assert f"publishing scm/{robot}/teacher" in out and "-> v " in out, out[:2000]  # it says what it does
    with lock:
        methods = {c.method for c in got["cmd"]}
        limits = list(got["limits"])
        status = got["status"][-1] if got["status"] else None
    assert progress > 0.25, (f"the robot covered only {progress:.0%} of the path; the station said "
                             f"{status.text if status else None!r}, sent {len(got['cmd'])} commands" + children)
    assert methods & MAPPED  # the station mapped the external teacher's commands, not passed them through
    assert limits and limits[-1].version >= 2  # the learned limits reached the teacher as they changed
    assert status is not None and status.counters.get("malformed_teacher", 0) == 0
    # what a transfer-only station sends: mapped (SC, or its affine/barycentric fallback where an SC map fails),
    # direct, perturbed or a stop; never a calibration command
    assert {c.method for c in got["cmd"]} <= {"scm", "affine", "barycentric", "direct", "perturb", "stop"}
