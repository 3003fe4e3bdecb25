"""Opening Zenoh sessions (:mod:`bridge.nodes.zsession`): what a configuration made here holds, a lab's file
overridden by ``--listen``/``--connect``, a file that cannot be read as one line, TLS told from plain TCP, and
:func:`open_session` with real sessions on free 127.0.0.1 ports: a tool's one try, a service that waits for its
router (and says so to systemd), and one told to stop while it waits.

Every integration test opens its sessions with this module; the nodes' use of the NO_TLS warning is tested in
tests/integration/test_acts.py; a certificate of another CA named as such in tests/integration/test_zenoh_acl.py."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time

import pytest
import zenoh

from bridge.core.errors import UsageError
from bridge.nodes.zsession import NO_TLS_WARNING, config_error, free_port, make_config, open_session, secured, tcp


def _get(conf: zenoh.Config, key: str):
    return json.loads(conf.get_json(key))


def test_free_port_is_a_tcp_port_that_can_be_bound_now() -> None:
    port = free_port()
    assert 1024 <= port <= 65535
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", port))
    assert tcp(port) == f"tcp/127.0.0.1:{port}" and tcp(7447, "10.0.0.2") == "tcp/10.0.0.2:7447"


def test_the_defaults_are_explicit_endpoints_no_scouting_no_shared_memory_and_quick_retries() -> None:
    conf = make_config(mode="client", connect=["tcp/127.0.0.1:1"], listen=[])
    assert _get(conf, "mode") == "client"
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:1"] and _get(conf, "listen/endpoints") == []
    assert _get(conf, "scouting/multicast/enabled") is False
    assert _get(conf, "transport/shared_memory/enabled") is False
    retry = _get(conf, "connect/retry")
    assert (retry["period_init_ms"], retry["period_max_ms"]) == (50, 500)
    assert _get(make_config(), "mode") == "peer"


def test_an_unknown_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="zenoh mode must be peer, client or router, not 'server'"):
        make_config(mode="server")


def test_a_labs_file_is_read_and_the_command_lines_endpoints_override_its_own(tmp_path) -> None:
    f = tmp_path / "lab.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7447"] },\n'
                 '  listen: { endpoints: ["tcp/127.0.0.1:7448"] } }\n')
    conf = make_config(config_file=f)
    assert _get(conf, "mode") == "client" and _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "transport/shared_memory/enabled") is False  # off unless the file says otherwise
    conf = make_config(config_file=str(f), connect=["tcp/127.0.0.1:9"], listen=["tcp/127.0.0.1:10"])
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:9"]
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:10"]
    f.write_text('{ mode: "client", transport: { shared_memory: { enabled: true } } }\n')
    assert _get(make_config(config_file=f), "transport/shared_memory/enabled") is True  # the lab's choice stands


@pytest.mark.parametrize("text", [None, "{ mode: ", "{ nonsense_key: 1 }", b"\xff\xfe"])
def test_a_file_that_cannot_be_used_is_one_line_naming_it(tmp_path, text) -> None:
    f = tmp_path / "bad.json5"
    if isinstance(text, bytes):
        f.write_bytes(text)
    elif text is not None:
        f.write_text(text)
    with pytest.raises(UsageError) as err:
        make_config(config_file=f)
    line = str(err.value)
    said = line.removeprefix(f"--zenoh-config {f}: ")
    assert said != line and "\n" not in line and 0 < len(said) <= 300  # the path is the machine's: bound what is said
    assert "lib.rs" not in said and ".cargo" not in said  # where in zenoh's source it was raised tells a lab nothing


def test_zenohs_complaints_become_one_line_saying_where() -> None:
    serde = ('JSON error: Message { msg: "unknown field `nonsense_key`, expected one of `id`, `mode`", location: '
             "Some(Location { line: 1, column: 3 }) } at /root/.cargo/git/x/commons/zenoh-config/src/lib.rs:1484.")
    assert config_error(serde) == "line 1, column 3: unknown field `nonsense_key`, expected one of `id`, `mode`"
    pest = (" --> 1:9\n  |\n1 | { mode: \n  |         ^---\n  |\n  = expected array, boolean, null, number, object, "
            "or string at /root/.cargo/git/x/commons/zenoh-config/src/lib.rs:1486.")
    assert config_error(pest) == "line 1, column 9: expected array, boolean, null, number, object, or string"
    assert config_error("Empty config file at /root/.cargo/x/lib.rs:1475.") == "Empty config file"
    long = config_error("x" * 1000)
    assert len(long) == 300 and long.endswith("...")


def test_secured_means_tls_only_with_a_ca_to_check_the_router(tmp_path) -> None:
    assert not secured(make_config())
    conf = make_config()
    conf.insert_json5("transport/link/protocols", '["tls"]')
    assert not secured(conf)  # TLS but no CA: nothing checks who answers
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tmp_path / "ca.crt")))
    assert secured(conf)
    conf.insert_json5("transport/link/protocols", '["tls", "tcp"]')
    assert not secured(conf)  # plain TCP allowed beside it


def test_a_tool_tries_once_and_a_router_that_is_not_there_is_one_line() -> None:
    port = free_port()
    with pytest.raises(UsageError) as err:
        open_session(make_config(mode="client", connect=[tcp(port)]))
    text = str(err.value)
    assert text.startswith(f"cannot reach the Zenoh router at tcp/127.0.0.1:{port} (")
    assert "scmbridge doctor" in text and " at /" not in text and "\n" not in text


def test_a_service_stopped_while_waiting_says_so(caplog) -> None:
    stop = threading.Event()
    stop.set()
    port = free_port()
    with caplog.at_level(logging.WARNING, "scmbridge.zenoh"), pytest.raises(UsageError) as err:
        open_session(make_config(mode="client", connect=[tcp(port)]), wait=stop, what="station")
    assert str(err.value) == f"stopped while waiting for the Zenoh router at tcp/127.0.0.1:{port}"
    assert f"station: {NO_TLS_WARNING}" in caplog.text  # a service without TLS says who may command it
    assert "station: cannot reach the Zenoh router" in caplog.text and "retrying" in caplog.text


def test_a_service_waits_for_its_router_tells_systemd_and_connects_once_it_is_up(tmp_path, monkeypatch) -> None:
    port = free_port()
    notify = tmp_path / "notify"
    got: dict = {}
    stop = threading.Event()
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as srv:
        srv.bind(str(notify))
        srv.settimeout(20.0)
        monkeypatch.setenv("NOTIFY_SOCKET", str(notify))

        def service() -> None:
            try:
                got["session"] = open_session(make_config(mode="client", connect=[tcp(port)]), wait=stop)
            except Exception as exc:  # reported below
                got["error"] = exc

        t = threading.Thread(target=service, daemon=True)
        t.start()
        try:
            # the service's first failed try: it tells systemd what it waits for
            assert srv.recv(1024) == f"STATUS=waiting for the Zenoh router at tcp/127.0.0.1:{port}".encode()
            with zenoh.open(make_config(mode="router", listen=[tcp(port)])) as router:
                t.join(20)
                assert not t.is_alive() and "error" not in got, got
                with got["session"] as s:
                    assert str(s.zid()) != str(router.zid())
                    peers = [str(z) for z in s.info.routers_zid()]
                    assert str(router.zid()) in peers  # connected to that router
        finally:
            stop.set()
            t.join(20)


def test_two_sessions_on_loopback_reach_each_other_and_close() -> None:
    port = free_port()
    with zenoh.open(make_config(listen=[tcp(port)])) as a, open_session(make_config(connect=[tcp(port)])) as b:
        a.declare_queryable("scmtest/echo", lambda q: q.reply("scmtest/echo", b"pong"))
        replies: list[bytes] = []
        deadline = time.monotonic() + 20.0  # the peers find each other within ~0.1 s quiet; bounded for a busy machine
        while not replies and time.monotonic() < deadline:
            # a get with no route to the queryable yet returns at once, empty: poll until the route is there
            replies = [r.ok.payload.to_bytes() for r in b.get("scmtest/echo", timeout=0.5) if r.ok is not None]
            if not replies:
                time.sleep(0.05)
        assert replies == [b"pong"]


def test_a_lab_zenoh_file_gets_the_safe_defaults_it_does_not_state(tmp_path) -> None:
    """Finding: a ``--zenoh-config`` without mode, listen or scouting ran the driver host and the station as a Zenoh
    peer listening on every interface with multicast scouting on. What the file does not state gets the built-in
    safe values; what it states is kept; a FIFO given as the file is refused without blocking."""
    import json
    import os

    from bridge.core.errors import UsageError
    from bridge.nodes.zsession import make_config

    bare = tmp_path / "bare.json5"
    bare.write_text('{ connect: { endpoints: ["tcp/127.0.0.1:7447"] } }\n')
    conf = make_config(config_file=bare)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    peer = tmp_path / "peer.json5"
    peer.write_text('{ mode: "peer", scouting: { multicast: { enabled: true } } }\n')
    conf = make_config(config_file=peer)
    assert json.loads(conf.get_json("mode")) == "peer"  # stated: kept
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]  # not stated: loopback only
    fifo = tmp_path / "fifo.json5"
    os.mkfifo(fifo)
    with pytest.raises(UsageError, match="not a regular file"):
        make_config(config_file=fifo)
