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
