"""sim_learner/emulator.py: ``scmbridge learner``, a software learner behind a vehicle link as its own process.

Its processes are started by the integration tests (tests/integration/test_udp_link.py checks ``--peer`` end to end;
tests/repo/test_architecture.py that its links are the registry's emulated ones). Here, in this process: the
command line (``--peer``, the defaults), the refusals made before anything starts, and one short run of the CAN
learner on a virtual bus, its controllers heard on that bus."""

from __future__ import annotations

import argparse
import signal
import struct
import uuid

import can
import pytest

from bridge.core.errors import UsageError
from sim_learner import emulator as E
from sim_learner.udp_robot import DEFAULT_PEER


def _parse(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    E.arguments(ap)
    return ap.parse_args(list(argv))


def test_peer_is_host_and_port_or_first_and_defaults_to_the_drivers_address() -> None:
    assert E._peer_arg(None) == DEFAULT_PEER
    assert E._peer_arg("first") == "first"
    assert E._peer_arg("10.0.0.7:47801") == ("10.0.0.7", 47801)
    assert E._peer_arg("[::1]:9000") == ("::1", 9000)
    for bad in ("10.0.0.7", ":47801", "host:port", "host:0", "host:65536", "first:1:"):
        with pytest.raises(UsageError, match="expected HOST:PORT .* or 'first'"):
            E._peer_arg(bad)


def test_the_command_lines_defaults() -> None:
    a = _parse("--link", "udp")
    assert (a.host, a.port, a.model, a.x0, a.noise, a.duration) == ("127.0.0.1", None, "mpc", (0.0, 0.0, 0.0), 0.0,
                                                                    None)
    assert (a.v_max, a.omega_max, a.watchdog, a.peer, a.key_file) == (1.0, 2.0, 0.5, None, None)
    assert sorted(E.EMULATORS) == ["can", "mavlink", "udp"]
    assert _parse("--link", "can", "--x0", "1,2,0.5").x0 == (1.0, 2.0, 0.5)
    with pytest.raises(SystemExit):
        _parse("--link", "serial")
    with pytest.raises(SystemExit):
        _parse("--link", "can", "--duration", "0")


@pytest.mark.parametrize("extra,match", [
    (["--peer", "nowhere"], "expected HOST:PORT"),
    (["--v-max", "0"], "must be positive"),
    (["--omega-max", "inf"], "must be positive"),
    (["--watchdog", "60"], "must be positive"),
])
def test_a_udp_learners_mistake_is_refused_before_anything_starts(extra: list[str], match: str) -> None:
    with pytest.raises(UsageError, match=match):
        E.run(_parse("--link", "udp", "--port", "1", *extra))


def test_the_can_learner_runs_its_two_controllers_on_the_bus_for_its_duration(capsys) -> None:
    channel = f"emu-{uuid.uuid4().hex[:8]}"
    spy = can.Bus(interface="virtual", channel=channel)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert E.run(_parse("--link", "can", "--interface", "virtual", "--channel", channel, "--duration", "0.3")) == 0
        nodes = set()
        while (f := spy.recv(timeout=0.0)) is not None:
            if f.arbitration_id & 0x1F == 0x01:  # Heartbeat
                err, state, _, _ = struct.unpack("<IBBBx", bytes(f.data))
                assert (err, state) == (0, 1)  # no error, IDLE: nobody armed them
                nodes.add(f.arbitration_id >> 5)
        assert nodes == {0, 1}
        assert f"learner on virtual:{channel}, model mpc" in capsys.readouterr().out
    finally:
        spy.shutdown()
        for s, h in handlers.items():
            signal.signal(s, h)
