"""The live view, checked in a real client: `scmbridge view` as its own process serves the Foxglove WebSocket
protocol (subprotocols foxglove.sdk.v1 and foxglove.websocket.v1); a WebSocket client subscribes the way Foxglove
does and receives the robot's pose, its scene and its commands and health as they are published on Zenoh."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import time

import pytest

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import spawn, stop_group

websockets = pytest.importorskip("websockets.sync.client")


def _port(proc, timeout: float = 30.0) -> int:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        line = proc.stdout.readline().decode()
        if "ws://" in line:
            return int(line.split("ws://", 1)[1].split()[0].rsplit(":", 1)[1])
    raise AssertionError("scmbridge view did not say where it serves")


@pytest.mark.timeout(90)
@pytest.mark.parametrize("subprotocol", ["foxglove.sdk.v1", "foxglove.websocket.v1"])
def test_a_foxglove_client_sees_pose_scene_commands_and_health_live(tmp_path, subprotocol: str) -> None:
    """Both names of the protocol: the SDK's, and the first one (Lichtblick, older Foxglove Studio), which the SDK's
    server alone answered with HTTP 400 (finding, issue 32)."""
    zport, robot = free_port(), f"lv{os.getpid()}"
    with open_session(make_config(mode="router", listen=[tcp(zport)])) as session:
        view = spawn(["view", "--robot", robot, "--port", "0", "--mode", "client", "--connect", tcp(zport),
                      "--duration", "60"], subprocess.PIPE)
        try:
            port = _port(view)
            with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol], open_timeout=10) as ws:
                assert ws.subprotocol == subprotocol
                hello = json.loads(ws.recv(timeout=10))
                assert hello["op"] == "serverInfo" and hello["name"] == "scmbridge", hello
                keys = M.Keys(robot)
                channels: dict[str, dict] = {}
                subscribed: dict[int, str] = {}
                got: dict[str, list[bytes]] = {}
                wanted = [f"/{robot}/pose", f"/{robot}/scene", f"/{robot}/cmd", f"/{robot}/status/driver"]

                def read(deadline: float) -> None:
                    """Read every frame that has come (subscribing to each advertised channel) until none for 50 ms."""
                    while time.monotonic() < deadline:
                        try:
                            frame = ws.recv(timeout=0.05)
                        except TimeoutError:
                            return
                        if isinstance(frame, str):
                            msg = json.loads(frame)
                            if msg.get("op") == "advertise":
                                for ch in msg["channels"]:
                                    channels[ch["topic"]] = ch
                                    if ch["topic"] not in subscribed.values():
                                        sid = len(subscribed) + 1
                                        subscribed[sid] = ch["topic"]
                                        ws.send(json.dumps({"op": "subscribe",
                                                            "subscriptions": [{"id": sid, "channelId": ch["id"]}]}))
                        elif frame[0] == 0x01:  # messageData: opcode, subscription id u32, timestamp u64, payload
                            sid = struct.unpack_from("<I", frame, 1)[0]
                            got.setdefault(subscribed[sid], []).append(bytes(frame[13:]))

                # a named robot's channels are advertised as the client connects: wait for them (the event), then
                # drive; before, a channel made on the first sample raced the client's subscription
                t_end = time.monotonic() + 30
                while time.monotonic() < t_end and not all(t in channels for t in wanted):
                    read(t_end)
                assert all(t in channels for t in wanted), f"advertised: {sorted(channels)}"
                seq = 0
                while time.monotonic() < t_end and not all(len(got.get(t, [])) >= 2 for t in wanted):
                    # the robot drives: publish what a station and a driver host publish
                    now = time.monotonic()
                    session.put(keys.state, M.encode(M.LearnerState(stamp=now, seq=seq, x=0.01 * seq, y=0.5,
                                                                    theta=0.1)))
                    session.put(keys.cmd, M.encode(M.Command(stamp=now, seq=seq, v=0.25, omega=-0.1,
                                                             method="scm")))
                    session.put(M.status_key(robot, "driver"), M.encode(M.Status(
                        stamp=now, seq=seq, node="driver", ok=False, text="operator took control: mode HOLD")))
                    seq += 1
                    read(t_end)
        finally:
            stop_group(view)
    for t in wanted:
        assert got.get(t), f"no {t} reached the client (advertised: {sorted(channels)})"
    assert channels[f"/{robot}/pose"]["schemaName"] == "foxglove.PoseInFrame"
    assert channels[f"/{robot}/scene"]["schemaName"] == "foxglove.SceneUpdate"
    cmd = json.loads(got[f"/{robot}/cmd"][-1])
    assert (cmd["v"], cmd["omega"], cmd["method"]) == (0.25, -0.1, "scm")
    health = json.loads(got[f"/{robot}/status/driver"][-1])
    assert health["ok"] is False and "operator took control" in health["text"]


def test_the_front_lets_in_both_names_and_leaves_other_handshakes_to_the_sdk() -> None:
    """The front before the SDK's own server, in this process: a client offering only the first name is served
    (serverInfo, its name handed back); one offering neither gets the SDK's 400, as without the front."""
    import warnings

    from bridge.tools.ws_front import SubprotocolFront, translate_request, translate_response

    head, legacy = translate_request(b"GET / HTTP/1.1\r\nHost: h\r\n"
                                     b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n")
    assert legacy and b"foxglove.websocket.v1, foxglove.sdk.v1\r\n\r\n" in head, head
    answer = translate_response(b"HTTP/1.1 101 Switching Protocols\r\n"
                                b"sec-websocket-protocol: foxglove.sdk.v1\r\n\r\n")
    assert answer.endswith(b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n"), answer  # its CR LF kept

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import foxglove

    server = foxglove.start_server(name="front-test", host="127.0.0.1", port=0)
    front = SubprotocolFront("127.0.0.1", 0, server.port)
    try:
        for proto in ("foxglove.websocket.v1", "foxglove.sdk.v1"):
            with websockets.connect(f"ws://127.0.0.1:{front.port}", subprotocols=[proto], open_timeout=10) as ws:
                assert ws.subprotocol == proto and json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
        from websockets.exceptions import InvalidStatus

        with pytest.raises(InvalidStatus) as refused:
            websockets.connect(f"ws://127.0.0.1:{front.port}", subprotocols=["other.v1"], open_timeout=10)
        assert refused.value.response.status_code == 400
        assert front.legacy_clients == 1
    finally:
        front.stop()
        server.stop()
