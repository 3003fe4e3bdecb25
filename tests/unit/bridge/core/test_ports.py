"""A free port is drawn below the kernel's ephemeral range, where no port-0 socket or outgoing connection takes it
between the draw and the bind it is for (bridge/core/ports.py)."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from bridge.core import ports


@pytest.mark.parametrize("kind", [socket.SOCK_STREAM, socket.SOCK_DGRAM])
def test_a_free_port_binds_now_and_lies_below_the_ephemeral_range(kind: socket.SocketKind) -> None:
    low = ports.ephemeral_low()
    drawn = {ports.free_port(kind=kind) for _ in range(20)}
    assert all(ports.LOWEST <= p < low for p in drawn) and len(drawn) > 1  # drawn, not the same port every time
    for p in drawn:
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", p))


def test_a_port_taken_meanwhile_is_passed_over(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        taken.bind(("127.0.0.1", 0))
        probe.bind(("127.0.0.1", 0))
        busy, free = taken.getsockname()[1], probe.getsockname()[1]
        probe.close()
        draws = [busy, busy, free]
        monkeypatch.setattr(ports._draw, "randrange", lambda lo, hi: draws.pop(0))
        monkeypatch.setattr(ports, "ephemeral_low", lambda: 65535)
        assert ports.free_port(kind=socket.SOCK_DGRAM) == free and draws == []


def test_without_room_below_the_range_or_a_readable_range_the_os_picks(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "range").write_text("garbage")
    assert ports.ephemeral_low(tmp_path / "range") == 32768 == ports.ephemeral_low(tmp_path / "missing")
    (tmp_path / "range").write_text("1024\t65535\n")
    assert ports.ephemeral_low(tmp_path / "range") == 1024
    monkeypatch.setattr(ports, "ephemeral_low", lambda: 10500)
    p = ports.free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", p))
