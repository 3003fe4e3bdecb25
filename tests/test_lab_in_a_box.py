"""A lab in a box: the secure deployment exactly as deploy/README.md lays it out, on loopback. `deploy lab` makes a CA
and the certificates, the router's TLS + access-control config (`scmbridge router`, a process of its own) and the
clients' configs; the station, a robot's driver host and the operator's tools are TLS clients: a person engages the
robot, starts the mission, sees it drive in `status --all`, stops it with `estop --all`; the observer sees everything
and can change nothing, and is told so ("denied", exit 3), not "nobody answered". Findings this answers: under the
lab's TLS + access control `estop --all` did nothing and the operator's tools saw nothing; an observer's engage said
"no driver host answered"."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port
from bridge.tools.procs import Children

ROBOT = "rover1"


def _scm(*args: str, timeout: float = 90) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args], capture_output=True, text=True, timeout=timeout)


def _until(fn, timeout: float, step: float = 0.5):
    t_end = time.monotonic() + timeout
    while True:
        res = fn()
        if res or time.monotonic() > t_end:
            return res
        time.sleep(step)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
@pytest.mark.timeout(240)
def test_a_secure_lab_on_loopback_is_driven_and_stopped_by_its_operator(tmp_path: Path) -> None:
    # the whole lab in one command (the certificates are used where they were made)
    made = _scm("deploy", "lab", "--robots", ROBOT, "--station-address", "127.0.0.1", "--port", str(free_port()),
                "--certs", str(tmp_path / "tls"), "--out", str(tmp_path))
    assert made.returncode == 0, made.stderr
    z = {n: ["--zenoh-config", str(tmp_path / f"{n}.json5")] for n in (ROBOT, "operator", "observer")}
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    with Children() as kids:
        kids.spawn(["router", "--zenoh-config", str(tmp_path / "router.json5"), "--duration", "220"],
                   subprocess.DEVNULL)
        kids.spawn(["station", "--robot", ROBOT, "--zenoh-config", str(tmp_path / "station-client.json5"), "--store",
                    str(tmp_path / "pairs.bin"), "--duration", "200"], subprocess.DEVNULL)
        kids.spawn(["driver", "--link", "can", "--emulate", "--x0", x0, "--robot", ROBOT, *z[ROBOT], "--duration",
                    "200"], subprocess.DEVNULL)
        # the operator sees both nodes: idle and waiting for a person
        def both() -> subprocess.CompletedProcess | None:
            r = _scm("status", "--all", *z["operator"])
            rows = {tuple(ln.split()[:3]) for ln in r.stdout.splitlines()}
            return r if (ROBOT, "station", "idle") in rows and any(x[:2] == (ROBOT, "driver") for x in rows) else None

        seen = _until(both, 60)
        assert seen and "waiting" in seen.stdout, seen and seen.stdout + seen.stderr
        for cmd in (["engage", "--robot", ROBOT], ["mission", "start", "--robot", ROBOT]):
            res = _scm(*cmd, *z["operator"])
            assert res.returncode == 0, res.stdout + res.stderr
        driving = _until(lambda: (r := _scm("status", "--robot", ROBOT, *z["observer"])).returncode == 0 and r, 60)
        assert driving and "driving" in driving.stdout, driving and driving.stdout + driving.stderr
        # the observer can change nothing, and is told it is denied (exit 3), not that nobody answered (exit 2)
        for cmd in (["engage", "--robot", ROBOT, "--release"], ["mission", "pause", "--robot", ROBOT],
                    ["estop", "--robot", ROBOT]):
            res = _scm(*cmd, "--timeout", "2", *z["observer"])
            assert res.returncode == 3 and "denied: identity 'observer' (role observer)" in res.stderr, res.stderr
        # calibrate drives as the station does: with the operator's identity it is denied at once
        res = _scm("calibrate", "--robot", ROBOT, *z["operator"])
        assert res.returncode == 3 and "station's identity" in res.stderr, res.stderr
        # the preflight through the lab's TLS and rules: the operator's identity sees both nodes
        doc = _scm("doctor", *z["operator"])
        assert doc.returncode == 0 and "ok    reach" in doc.stdout and "1 driver hosts answer" in doc.stdout, doc.stdout
        assert "ok    tls" in doc.stdout and "FAIL" not in doc.stdout, doc.stdout
        # the operator stops every robot
        res = _scm("estop", "--all", *z["operator"])
        assert res.returncode == 0 and f"{ROBOT}/driver-can: LATCHED by operator" in res.stdout, res.stdout + res.stderr
        stopped = _until(lambda: "estop latched by operator" in _scm("status", "--all", *z["observer"]).stdout, 30)
        assert stopped
