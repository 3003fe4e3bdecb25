"""``scmbridge router``: the lab's Zenoh router as a process of its own, so that the operator's tools do not depend
on the station (issue 32, item 4; deploy/README.md).

Finding this answers: in the documented layout the station *was* the router; when it stopped, ``status`` and
``estop --all`` exited 2 ("cannot reach the Zenoh router") and the robots stopped only by their deadman. Here the
router, a station and a driver host are real processes on free 127.0.0.1 ports, the station and the driver host
clients of the router; the station is killed without a word (SIGKILL) and the operator's tools still answer:
``status`` says the station is missing (exit 1, docs/CLI.md) and ``estop --all`` latches the robot (exit 0)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port, tcp
from bridge.tools.procs import Children, said
from tests.lab import start_router
from tests.wait import until


def _tool(port: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args, "--mode", "client", "--connect", tcp(port)],
                          capture_output=True, text=True, timeout=timeout)


def test_the_router_refuses_to_listen_on_nothing_or_everything() -> None:
    for argv in (["router"], ["router", "--listen", "tcp/0.0.0.0:7447"]):
        res = subprocess.run([sys.executable, "-m", "bridge", *argv, "--duration", "1"], capture_output=True,
                             text=True, timeout=60)
        assert res.returncode == 2 and "listen" in res.stderr and "Traceback" not in res.stderr, res.stderr


@pytest.mark.timeout(240)
def test_status_and_estop_all_work_while_the_station_is_down(tmp_path) -> None:
    port = free_port()
    robot = f"k{os.getpid()}"
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    client = ["--mode", "client", "--connect", tcp(port)]
    with Children() as kids:
        router = start_router(kids, "--listen", tcp(port))
        station = kids.spawn(["station", "--robot", robot, "--store", str(tmp_path / "pairs.bin"), *client,
                              "--duration", "220"])
        kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, "--robot", robot, *client,
                    "--duration", "220"], out=subprocess.DEVNULL)

        def both_heard() -> subprocess.CompletedProcess | None:
            res = _tool(port, "status", "--robot", robot)
            rows = [ln.split()[:2] for ln in res.stdout.splitlines()]
            return res if [robot, "station"] in rows and [robot, "driver"] in rows else None

        seen = until(both_heard, 150, 0.5)
        assert seen, kids.said()

        # the station dies without a word; the router, and with it every other node, stays
        os.killpg(station.pid, signal.SIGKILL)
        station.wait(10)

        res = _tool(port, "status", "--robot", robot)
        rows = {tuple(ln.split()[:3]) for ln in res.stdout.splitlines()}
        assert res.returncode == 1, (res.stdout, res.stderr)  # docs/CLI.md: 1 when a robot is not driving
        assert (robot, "station", "missing") in rows and any(r[:2] == (robot, "driver") for r in rows), res.stdout

        stop = _tool(port, "estop", "--all", "--timeout", "10")
        assert stop.returncode == 0, (stop.stdout, stop.stderr)
        assert f"{robot}/driver-can: LATCHED by operator" in stop.stdout, stop.stdout
        # a release from a source the host does not accept is answered, kept latched, and the tool says why
        bad = _tool(port, "estop", "--robot", robot, "--release", "--source", "visitor", "--timeout", "2")
        assert bad.returncode == 1 and "estop_release_sources" in bad.stderr and "'visitor'" in bad.stderr, bad
        assert router.poll() is None, said(router)


def test_the_router_tells_systemd_it_is_ready_with_what_it_listens_on(tmp_path) -> None:
    """scmbridge-router.service is Type=notify: READY=1 once it listens, its status naming the endpoint and the access
    control; STOPPING=1 on SIGTERM, and a clean exit."""
    import socket

    port, path = free_port(), tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv, Children() as kids:
        srv.bind(str(path))
        srv.settimeout(60.0)
        router = kids.spawn(["router", "--listen", tcp(port)], subprocess.DEVNULL,
                            env={**os.environ, "NOTIFY_SOCKET": str(path)})
        got = srv.recv(1024).decode()
        assert got.startswith("READY=1\nSTATUS=listening on ") and tcp(port) in got, got
        assert "no access control" in got
        os.killpg(router.pid, signal.SIGTERM)
        assert srv.recv(1024) == b"STOPPING=1"
        assert router.wait(20) == 0
