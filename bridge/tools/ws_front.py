"""The live view's door for WebSocket clients of the Foxglove protocol's first name (``scmbridge view``).

The Foxglove SDK's server (foxglove-sdk 0.30, Rust inside) accepts only the subprotocols ``foxglove.sdk.v1`` and
``foxglove.sdk.v1.1`` and answers a client that offers only ``foxglove.websocket.v1`` (Lichtblick, Foxglove Studio
before the SDK, the ws-protocol libraries) with HTTP 400 "Missing expected sec-websocket-protocol header": its name
is fixed in the compiled server and no option changes it. The messages are the same protocol (the SDK's server
speaks the ws-protocol specification's serverInfo, advertise, subscribe, messageData, ... under its new name), so
this front listens where the view was asked to, lets each connection's handshake offer the SDK's name as well as
the client's, hands back to the client the name it offered, and from then on copies the bytes both ways unchanged.
A client that offers the SDK's name goes through untouched; one that offers neither gets the SDK's own 400.
"""

from __future__ import annotations

import logging
import re
import socket
import threading

log = logging.getLogger("scmbridge.view")

#: the name Foxglove's WebSocket protocol had before the SDK (ws-protocol's spec), and the SDK server's
LEGACY, SDK = "foxglove.websocket.v1", "foxglove.sdk.v1"
#: an upgrade request or response larger than this is not one, bytes
MAX_HEAD = 16384
#: s a client may take to send its handshake, and the SDK's server to answer it
HANDSHAKE_TIMEOUT_S = 5.0

#: a Sec-WebSocket-Protocol header line (its value up to, not with, the line's CR LF)
_PROTOCOL = re.compile(rb"^sec-websocket-protocol:[ \t]*([^\r\n]*)", re.I | re.M)


def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """An HTTP head (up to and with its blank line) and whatever came after it; ValueError if there is none."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("closed before the end of the HTTP head")
        data += chunk
        if len(data) > MAX_HEAD:
            raise ValueError("HTTP head too large")
    end = data.index(b"\r\n\r\n") + 4
    return data[:end], data[end:]


def offered(head: bytes) -> list[str]:
    """The subprotocols a WebSocket upgrade request offers (every ``Sec-WebSocket-Protocol`` line, in order)."""
    return [p.strip() for line in _PROTOCOL.findall(head) for p in line.decode("latin-1").split(",") if p.strip()]


def translate_request(head: bytes) -> tuple[bytes, bool]:
    """The request as the SDK's server needs it, and whether the client spoke only the legacy name: a client that
    offers ``foxglove.websocket.v1`` and no ``foxglove.sdk.v1*`` also offers the SDK's name."""
    names = offered(head)
    if LEGACY not in names or any(n.startswith(SDK) for n in names):
        return head, False
    lines = [ln for ln in head[:-4].split(b"\r\n") if not _PROTOCOL.match(ln)]
    lines.append(f"Sec-WebSocket-Protocol: {', '.join([*names, SDK])}".encode("latin-1"))
    return b"\r\n".join(lines) + b"\r\n\r\n", True


def translate_response(head: bytes) -> bytes:
    """The SDK's answer to a legacy client: the subprotocol it chose named as the client offered it."""
    return _PROTOCOL.sub(f"Sec-WebSocket-Protocol: {LEGACY}".encode("latin-1"), head, count=1)


class SubprotocolFront:
    """Listens on ``host:port`` (0: a free port, then :attr:`port`) and passes each connection to the SDK's server
    on ``127.0.0.1:inner_port``, naming the subprotocol each side knows (module docstring). One thread accepts,
    two per connection copy; :meth:`stop` closes everything."""

    def __init__(self, host: str, port: int, inner_port: int) -> None:
        self.inner_port = inner_port
        self.listener = socket.create_server((host, port))
        self.listener.settimeout(0.2)  # accept() looks at stopped this often
        self.port = self.listener.getsockname()[1]
        self.lock = threading.Lock()
        self.open: set[socket.socket] = set()
        self.stopped = False
        self.legacy_clients = 0
        self.thread = threading.Thread(target=self._accept, name="view-front", daemon=True)
        self.thread.start()

    def _accept(self) -> None:
        while not self.stopped:
            try:
                client, _ = self.listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed by stop()
            client.settimeout(None)
            threading.Thread(target=self._serve, args=(client,), name="view-front-conn", daemon=True).start()

    def _track(self, *socks: socket.socket) -> bool:
        with self.lock:
            if self.stopped:
                return False
            self.open.update(socks)
            return True

    def _serve(self, client: socket.socket) -> None:
        inner = None
        try:
            client.settimeout(HANDSHAKE_TIMEOUT_S)
            head, rest = _read_head(client)
            head, legacy = translate_request(head)
            inner = socket.create_connection(("127.0.0.1", self.inner_port), timeout=HANDSHAKE_TIMEOUT_S)
            if not self._track(client, inner):
                raise ValueError("the view is stopping")
            inner.sendall(head + rest)
            answer, more = _read_head(inner)
            if legacy:
                answer = translate_response(answer)
                with self.lock:
                    self.legacy_clients += 1
                log.info("a %s client connected (served by the SDK's %s)", LEGACY, SDK)
            client.sendall(answer + more)
            client.settimeout(None)
            inner.settimeout(None)
        except (OSError, ValueError) as exc:
            log.debug("view connection dropped in its handshake: %s", exc)
            self._close(client, inner)
            return
        threading.Thread(target=self._copy, args=(inner, client), name="view-front-copy", daemon=True).start()
        self._copy(client, inner)

    def _copy(self, src: socket.socket, dst: socket.socket) -> None:
        """Bytes from ``src`` to ``dst`` until either side closes; then both are closed (the other copy ends)."""
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        self._close(src, dst)

    def _close(self, *socks: socket.socket | None) -> None:
        for s in socks:
            if s is None:
                continue
            with self.lock:
                self.open.discard(s)
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def stop(self) -> None:
        with self.lock:
            self.stopped = True
            left = list(self.open)
        self.thread.join(2.0)
        self.listener.close()
        self._close(*left)


__all__ = ["LEGACY", "SDK", "SubprotocolFront", "offered", "translate_request", "translate_response"]
