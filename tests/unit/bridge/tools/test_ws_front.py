"""bridge/tools/ws_front.py: the live view's handshake translation (which subprotocols a request offers, the request
as the Foxglove SDK's server needs it, its answer as the client offered it), the HTTP head reader on a real socket
pair, and a front whose inner server is gone. A real websockets client through the front to the SDK's server (both
names served, any other refused with the SDK's 400) is in tests/integration/test_live_view.py."""

from __future__ import annotations

import socket

import pytest

from bridge.tools import ws_front
from bridge.tools.ws_front import (
    LEGACY,
    MAX_HEAD,
    SDK,
    SubprotocolFront,
    offered,
    translate_request,
    translate_response,
)


def _request(*protocol_lines: str) -> bytes:
    lines = ["GET / HTTP/1.1", "Host: 127.0.0.1:8765", "Upgrade: websocket", "Connection: Upgrade",
             *(f"Sec-WebSocket-Protocol: {p}" for p in protocol_lines), "Sec-WebSocket-Version: 13"]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def test_offered_names_come_from_every_protocol_line_in_order_whatever_its_case() -> None:
    head = _request("a.v1, b.v2", "c.v3")
    assert offered(head) == ["a.v1", "b.v2", "c.v3"]
    assert offered(b"GET / HTTP/1.1\r\nsec-websocket-PROTOCOL:x.v1,,  y.v1 \r\n\r\n") == ["x.v1", "y.v1"]
    assert offered(_request()) == []


def test_a_legacy_only_request_also_offers_the_sdks_name_and_keeps_every_other_header() -> None:
    head = _request(f"{LEGACY}, other.v1")
    out, legacy = translate_request(head)
    assert legacy and offered(out) == [LEGACY, "other.v1", SDK]
    assert out.endswith(b"\r\n\r\n") and out.count(b"\r\n\r\n") == 1
    kept = [ln for ln in head.split(b"\r\n") if ln and not ln.lower().startswith(b"sec-websocket-protocol")]
    assert all(ln in out.split(b"\r\n") for ln in kept)
    assert out.split(b"\r\n")[0] == b"GET / HTTP/1.1"


@pytest.mark.parametrize("names", [(SDK,), (f"{LEGACY}, {SDK}",), (f"{SDK}.1", LEGACY), ("other.v1",), ()])
def test_a_request_that_offers_the_sdks_name_or_not_the_legacy_one_is_passed_unchanged(names) -> None:
    head = _request(*names)
    assert translate_request(head) == (head, False)


def test_the_answer_names_the_legacy_protocol_once_keeping_the_line_end() -> None:
    answer = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n"
              b"X-Other: 1\r\n\r\n")
    out = translate_response(answer)
    assert out == answer.replace(b"foxglove.sdk.v1", LEGACY.encode())
    assert translate_response(b"HTTP/1.1 400 Bad Request\r\n\r\n") == b"HTTP/1.1 400 Bad Request\r\n\r\n"


def test_the_head_is_read_up_to_its_blank_line_and_the_rest_kept() -> None:
    a, b = socket.socketpair()
    with a, b:
        a.settimeout(5.0)
        b.sendall(b"GET / HTTP/1.1\r\nHost: h\r\n")
        b.sendall(b"\r\n\x81\x05hello")  # the head's end in a second segment, then a frame
        head, rest = ws_front._read_head(a)
        assert head == b"GET / HTTP/1.1\r\nHost: h\r\n\r\n" and rest == b"\x81\x05hello"


def test_a_head_cut_short_or_too_large_is_refused() -> None:
    a, b = socket.socketpair()
    with a, b:
        a.settimeout(5.0)
        b.sendall(b"GET / HTTP/1.1\r\n")
        b.shutdown(socket.SHUT_WR)
        with pytest.raises(ValueError, match="closed before the end of the HTTP head"):
            ws_front._read_head(a)
    a, b = socket.socketpair()
    with a, b:
        a.settimeout(5.0)
        b.sendall(b"X" * (MAX_HEAD + 4096))
        with pytest.raises(ValueError, match="too large"):
            ws_front._read_head(a)


def test_a_client_is_closed_when_the_inner_server_is_gone_and_stop_ends_the_front() -> None:
    gone = socket.create_server(("127.0.0.1", 0))
    inner_port = gone.getsockname()[1]
    gone.close()  # nothing listens there now
    front = SubprotocolFront("127.0.0.1", 0, inner_port)
    try:
        assert front.port > 0 and front.thread.is_alive()
        with socket.create_connection(("127.0.0.1", front.port), timeout=5.0) as c:
            c.sendall(_request(LEGACY))
            assert c.recv(1024) == b""  # closed, no answer: the handshake failed
        assert front.legacy_clients == 0
    finally:
        front.stop()
    assert not front.thread.is_alive() and front.open == set()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", front.port), timeout=1.0).close()
