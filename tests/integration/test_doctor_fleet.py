"""``scmbridge doctor`` asks the robots (finding: on the operator's console it read that console's own state
directory and reported another host's "rover1 released" latch; on a separate console it checked a directory that
has nothing to do with the robots). A real router, a real driver host (the emulated CAN learner) with its own state
directory, latched by the operator's estop; doctor runs with another state directory, holding a latch file that is
no running robot's."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bridge.nodes.zsession import free_port, tcp
from bridge.tools.procs import Children, said
from tests.lab import start_router
from tests.wait import until


def _scm(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args], capture_output=True, text=True, timeout=120,
                          env=env)


@pytest.mark.timeout(180)
def test_doctor_asks_each_robot_for_its_latch_and_reads_only_a_local_hosts_state(tmp_path) -> None:
    port, robot = free_port(), f"doc{os.getpid()}"
    client = ["--mode", "client", "--connect", tcp(port)]
    console = tmp_path / "console-state"
    console.mkdir(mode=0o700)
    (console / "estop-ghost.bin").write_bytes(b"a latch file left by a host that ran here once")
    env = {**os.environ, "SCMBRIDGE_STATE_DIR": str(console)}
    with Children() as kids:
        start_router(kids, "--listen", tcp(port))
        host = kids.spawn(["driver", "--link", "can", "--emulate", "--x0", "0,0,0", "--robot", robot, *client,
                           "--duration", "150"], env={**os.environ, "SCMBRIDGE_STATE_DIR": str(tmp_path / "robot")})
        assert until(lambda: "on link can" in said(host, 20000), 90, 0.2), said(host)
        res = _scm("estop", "--robot", robot, *client)
        assert res.returncode == 0, res.stdout + res.stderr
        doc = _scm("doctor", *client, "--duration", "1.5", env=env)
    lines = [ln for ln in doc.stdout.splitlines() if ln.split()[1:2] == ["robot"]]
    assert len(lines) == 1 and f"{robot} (driver host on this machine): estop latched by operator" in lines[0], \
        doc.stdout
    assert "ghost" not in doc.stdout, doc.stdout  # a file in this console's directory is no robot's latch
    latch = [ln for ln in doc.stdout.splitlines() if ln.split()[1:2] == ["latch"]]
    # the host runs here but keeps its latch elsewhere: this directory has none of it, and says so
    assert latch and all(robot in ln and "this machine's driver host" in ln for ln in latch), doc.stdout
