"""systemd's readiness protocol (:mod:`bridge.nodes.systemd`) on a real unix datagram socket: the fields of one call
make one datagram, an abstract socket (``@name``) is reached, and nothing ever raises. (READY, STATUS and STOPPING on
a plain socket, and the services' own use of them: tests/integration/test_systemd_notify.py.)"""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator

import pytest

from bridge.nodes import systemd


@pytest.fixture
def notify_socket(tmp_path, monkeypatch) -> Iterator[socket.socket]:
    """A socket standing where systemd's is, named in ``$NOTIFY_SOCKET``."""
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(str(path))
        srv.settimeout(5.0)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        yield srv


def test_the_fields_of_one_call_are_one_datagram_one_per_line(notify_socket) -> None:
    assert systemd.notify("READY=1", "STATUS=up", "MAINPID=1")
    assert notify_socket.recv(1024) == b"READY=1\nSTATUS=up\nMAINPID=1"
    assert systemd.ready()  # no status: READY alone
    assert notify_socket.recv(1024) == b"READY=1"


def test_a_newline_inside_a_field_never_starts_another_field(notify_socket) -> None:
    """A status naming a reason with a newline in it must not become a second assignment (``READY=1`` forged by a
    reason's text)."""
    assert systemd.status("waiting\nREADY=1")
    assert notify_socket.recv(1024) == b"STATUS=waiting READY=1"
    assert systemd.ready("a\nb")
    assert notify_socket.recv(1024) == b"READY=1\nSTATUS=a b"


def test_an_abstract_socket_is_reached(monkeypatch) -> None:
    name = f"scmbridge-test-notify-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind("\0" + name)
        srv.settimeout(5.0)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        assert systemd.stopping()
        assert srv.recv(1024) == b"STOPPING=1"


@pytest.mark.parametrize("where", ["", "missing", "file", "stream"])
def test_no_socket_or_one_that_cannot_be_reached_is_false_and_never_raises(where, tmp_path, monkeypatch) -> None:
    path = tmp_path / "notify"
    stream = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        if where == "":
            monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
        elif where == "missing":
            monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        elif where == "file":  # a plain file where the socket should be
            path.write_text("")
            monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        else:  # a socket of the wrong kind
            stream.bind(str(path))
            stream.listen(1)
            monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        assert systemd.ready("x") is False
        assert systemd.status("x") is False
        assert systemd.stopping() is False
    finally:
        stream.close()
