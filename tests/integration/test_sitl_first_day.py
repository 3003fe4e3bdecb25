"""docs/OPERATING.md, "First day with your rover", run as written against ArduPilot's Rover in SITL.

Every command of that section's fenced blocks runs here, in its order: the ``scmbridge`` ones word for word (with the
Zenoh endpoint of this test's router appended, and ``SCMBRIDGE_STATE_DIR`` a temporary directory), ``cp`` as a copy,
``mavproxy.py`` as the dev lock's MAVProxy (``python -m MAVProxy.mavproxy``, its console fed on standard input). The
radio is a pseudo-terminal whose far end is SITL's SERIAL1 (tests/ptyrelay.py): ``/dev/ttyUSB0`` is its path, and
``14550`` a free UDP port. The person's edits the prose asks for (the url, the key file, the companion's ids) are made
to the copied file; the lab's station runs as a service. Marked ``sitl``; bounded, everything cleaned up.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, free_udp_port
from sim_learner.sitl import Sitl
from tests.collect import Collector
from tests.integration.test_sitl import _sitl_binary
from tests.integration.test_sitl_radio import MavProxy
from tests.ptyrelay import PtyRelay

ROOT = Path(__file__).resolve().parents[2]
SECTION = "## First day with your rover"

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(300),
              pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None
                                 and not os.environ.get("SCMBRIDGE_SITL_REQUIRED"),
                                 reason="MAVProxy is not installed (it is in requirements/dev.txt)")]


def section_commands() -> list[str]:
    """The command lines of the section's fenced blocks, in order."""
    text = (ROOT / "docs" / "OPERATING.md").read_text()
    body = text[text.index(SECTION) + len(SECTION):]
    body = body[:body.index("\n## ")]
    return [ln.strip() for block in re.findall(r"```[a-z]*\n(.*?)```", body, flags=re.S)
            for ln in block.replace("\\\n", " ").splitlines() if ln.strip()]


def test_the_section_shows_the_first_day_in_order() -> None:
    words = [" ".join(shlex.split(c)[:3]) for c in section_commands()]
    assert words == ["cp deploy/driver.mavlink.example.toml driver-rover1.toml", "scmbridge keys mavlink",
                     "scmbridge config check", "scmbridge doctor --driver", "mavproxy.py --master /dev/ttyUSB0",
                     "scmbridge driver --link",
                     "scmbridge mission place", "scmbridge mission send", "scmbridge engage --robot",
                     "scmbridge mission start", "scmbridge estop --robot"], words


def _edit(path: Path, **values: str) -> None:
    """The person's edit of ``[link.mavlink]``: each ``key = value`` line set (added when missing)."""
    text = path.read_text()
    for key, value in values.items():
        line = f"{key} = {value}"
        text, n = re.subn(rf"(?m)^{key} = .*$", line, text)
        if not n:
            text = text.replace("[link.mavlink]\n", f"[link.mavlink]\n{line}\n")
    path.write_text(text)


def test_first_day_with_your_rover_runs_as_written(tmp_path: Path) -> None:
    commands = section_commands()
    port, udp = free_port(), free_udp_port()
    env = {**os.environ, "SCMBRIDGE_STATE_DIR": str(tmp_path / "state")}
    zenoh = ["--mode", "client", "--connect", tcp(port)]
    with Sitl(_sitl_binary(), model="rover-skid") as sitl, PtyRelay(int(sitl.driver_url.rsplit(":", 1)[1])) as pty, \
            open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        status = col.listen(M.status_key("rover1", "driver"), M.Status)
        station = col.listen(M.status_key("rover1", "station"), M.Status)
        gcs: MavProxy | None = None
        pilot = sitl.pilot  # what the vehicle reports, on its SERIAL0

        def words(cmd: str) -> list[str]:
            return shlex.split(cmd.replace("/dev/ttyUSB0", pty.path).replace("14550", str(udp)))

        def scm(cmd: str, timeout: float = 120) -> subprocess.CompletedProcess:
            args = words(cmd)[1:]
            zen = zenoh if args[0] in ("doctor", "mission", "engage", "estop") else []
            r = subprocess.run([sys.executable, "-m", "bridge", *args, *zen], capture_output=True, text=True,
                               timeout=timeout, cwd=tmp_path, env=env)
            assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
            return r

        def driver_state(pred, timeout: float) -> M.Status:
            assert col.wait(lambda: status and pred(status[-1]), timeout), \
                f"{[s.text for s in status[-3:]]}{kids.said()}"
            return status[-1]

        try:
            cfg = tmp_path / "driver-rover1.toml"
            for cmd in commands:
                w = words(cmd)
                if w[0] == "cp":
                    shutil.copy(ROOT / w[1], tmp_path / w[2])  # then the person's edits of step 1
                    _edit(cfg, url=f'"{pty.path}"', signing_key_file='"rover1-mavlink.key"')
                elif w[0] == "mavproxy.py":
                    gcs = MavProxy(pty.path, udp, tmp_path, argv=[sys.executable, "-m", "MAVProxy.mavproxy", *w[1:]])
                    assert gcs.expect("Detected vehicle 1:1", 30), gcs.said[-20:]
                    gcs.type("signing key PASSPHRASE")
                    # the person's edits of step 4: the radio is MAVProxy's, the host a companion computer
                    _edit(cfg, url=f'"udpin:127.0.0.1:{udp}"', source_system="1", source_component="191")
                elif w[1] == "driver":
                    kids.spawn([*w[1:], *zenoh, "--duration", "250"], env=env, cwd=tmp_path)
                    # the lab's station, as its service runs it
                    kids.spawn(["station", "--robot", "rover1", *zenoh, "--store", str(tmp_path / "pairs.bin"),
                                "--duration", "250"], env=env, cwd=tmp_path)
                    st = driver_state(lambda s: s.state == "waiting", 90)
                    assert "waiting for engage" in st.text or "waiting for the operator" in st.text, st.text
                    assert col.wait(lambda: bool(station), 120), f"the station did not start{kids.said()}"
                elif w[1:3] == ["mission", "place"]:
                    r = scm(cmd, 60)
                    assert "in frame 'ekf-origin'" in r.stdout, r.stdout
                elif w[1:3] == ["mission", "start"]:
                    scm(cmd, 60)
                    assert pilot.wait(lambda s: s.position is not None and math.hypot(s.position.vx, s.position.vy)
                                      > 0.1, 60), f"the rover did not drive{kids.said()}"
                    # the person takes it at the ground station: the host honours it
                    assert gcs is not None
                    gcs.type("mode HOLD")
                    st = driver_state(lambda s: "operator took control: mode HOLD" in s.text, 10)
                    assert not st.ok
                    assert pilot.wait(lambda s: s.mode == "HOLD" and math.hypot(s.position.vx, s.position.vy) < 0.05,
                                      15)
                elif w[1] == "engage":
                    scm(cmd, 60)
                    # the host answers once the autopilot ACKed the arming; the pilot's own view of it comes with the
                    # vehicle's next HEARTBEAT on SERIAL0 (1 Hz), so it is waited for, not read at once
                    assert pilot.wait(lambda s: s.mode == "GUIDED" and s.armed, 5), (pilot.mode, pilot.armed)
                elif w[1] == "estop":
                    r = scm(cmd, 60)
                    driver_state(lambda s: s.state == "estop", 10)
                    assert pilot.mode == "HOLD", pilot.mode  # the operator's mode is left as it is
                else:
                    r = scm(cmd)
                    if w[1] == "doctor":
                        assert "ok    signing  on:" in r.stdout, r.stdout
        finally:
            if gcs is not None:
                gcs.close()
