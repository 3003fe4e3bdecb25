"""The readiness protocol as systemd reads it: datagrams on $NOTIFY_SOCKET (a real unix socket here)."""

from __future__ import annotations

import socket

from bridge.nodes import systemd


def test_ready_status_and_stopping_reach_the_notify_socket(tmp_path, monkeypatch) -> None:
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(str(path))
        srv.settimeout(2.0)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        assert systemd.ready("driving")
        assert srv.recv(1024) == b"READY=1\nSTATUS=driving"
        assert systemd.status("waiting for\nthe vehicle")
        assert srv.recv(1024) == b"STATUS=waiting for the vehicle"
        assert systemd.stopping()
        assert srv.recv(1024) == b"STOPPING=1"


def test_without_systemd_nothing_happens(monkeypatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not systemd.ready()
    monkeypatch.setenv("NOTIFY_SOCKET", "/nonexistent/socket")
    assert not systemd.status("x")


def test_the_services_say_ready_once_really_up_and_what_they_wait_for(tmp_path) -> None:
    """Type=notify units: the station and the driver host send READY=1 once their session is open and (driver)
    the link is open, with a status line that says where they are; STOPPING=1 when they stop."""
    import os
    import subprocess

    from bridge.nodes.zsession import free_port, make_config, open_session, tcp
    from bridge.tools.procs import Children

    port, robot = free_port(), f"sd{os.getpid()}"
    path = tmp_path / "notify"
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port), "--duration", "30"]
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv, \
            open_session(make_config(mode="router", listen=[tcp(port)])), Children() as kids:
        srv.bind(str(path))
        srv.settimeout(60.0)
        env = {**os.environ, "NOTIFY_SOCKET": str(path)}
        host = kids.spawn(["driver", "--link", "can", "--emulate", *client], subprocess.DEVNULL, env=env)
        got = srv.recv(1024).decode()
        assert got.startswith("READY=1\nSTATUS=") and "waiting for engage" in got, got
        kids.spawn(["station", *client], subprocess.DEVNULL, env=env)
        got = srv.recv(1024).decode()
        assert got.startswith("READY=1\nSTATUS=") and "mission idle" in got, got
        host.terminate()
        assert srv.recv(1024) == b"STOPPING=1"
