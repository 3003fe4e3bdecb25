"""``scmbridge engage`` (:mod:`bridge.tools.engage`): its arguments, and :func:`ask` on one real Zenoh session whose
own queryable answers as a driver host would: every try stamped now with a new nonce, every answer decoded, what
does not decode skipped, nobody answering an empty list within the timeout. The command end to end against real
driver hosts is in tests/integration/test_engage.py and tests/integration/test_acts.py."""

from __future__ import annotations

import argparse
import time

import pytest
import zenoh

from bridge.core import wire as M
from bridge.nodes.zsession import make_config
from bridge.tools import engage


def _args(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    engage.arguments(ap)
    return ap.parse_args(list(argv))


def test_the_arguments_default_to_engaging_as_the_operator() -> None:
    a = _args("--robot", "rover1")
    assert (a.robot, a.release, a.clear_faults, a.source, a.timeout) == ("rover1", False, False, "operator", 40.0)
    a = _args("--robot", "r", "--release", "--clear-faults", "--source", "alice", "--timeout", "2")
    assert a.release and a.clear_faults and a.source == "alice" and a.timeout == 2.0
    for argv in ([], ["--robot", "a/b"], ["--robot", "r", "--timeout", "-1"]):
        with pytest.raises(SystemExit):
            _args(*argv)


def test_each_ask_is_stamped_fresh_and_every_hosts_answer_is_kept() -> None:
    asked: list[M.EngageRequest] = []

    def host(q: zenoh.Query) -> None:
        asked.append(M.decode(q.payload.to_bytes(), M.EngageRequest))
        q.reply("scm/r1/engage", M.encode(M.EngageState(stamp=1.0, node="driver", engaged=True, text="engaged")))

    def broken(q: zenoh.Query) -> None:  # a host whose answer does not decode
        q.reply("scm/r2/engage", b"\xc1 garbage")

    req = M.EngageRequest(stamp=5.0, source="alice", clear_faults=True)
    with zenoh.open(make_config()) as s:
        s.declare_queryable("scm/r1/engage", host)
        s.declare_queryable("scm/r2/engage", broken)
        before = time.time()
        got = [engage.ask(s, "r1", req, timeout=20.0) for _ in range(2)]
        assert engage.ask(s, "r2", req, timeout=0.5) == []  # what does not decode is skipped, never raised
    assert got == [[M.EngageState(stamp=1.0, node="driver", engaged=True, text="engaged")]] * 2
    assert len(asked) == 2 and asked[0].nonce != asked[1].nonce  # a new nonce each time: taken fresh and once
    for a in asked:
        assert a.source == "alice" and a.clear_faults and a.engaged and before <= a.wall_time <= time.time()


def test_nobody_answering_is_an_empty_list_once_the_timeout_passes() -> None:
    with zenoh.open(make_config()) as s:
        t0 = time.monotonic()
        assert engage.ask(s, "nobody", M.EngageRequest(stamp=0.0), timeout=0.5) == []
        assert time.monotonic() - t0 < 5.0


def test_two_driver_hosts_of_one_robot_each_answer() -> None:
    """Finding (tests/unit/bridge/tools/test_estop.py): Zenoh's default reply consolidation kept one reply per key,
    so of two hosts answering on ``scm/<robot>/engage`` the tool printed one. Clients of one router on loopback."""
    from bridge.nodes.zsession import free_port, tcp

    port = free_port()
    client = make_config(mode="client", connect=[tcp(port)])
    with zenoh.open(make_config(mode="router", listen=[tcp(port)])) as _router, \
            zenoh.open(client) as h1, zenoh.open(client) as h2, zenoh.open(client) as tool:
        for s, node in ((h1, "driver"), (h2, "driver2")):
            st = M.EngageState(stamp=1.0, node=node, engaged=True)
            s.declare_queryable(M.key("r1", "engage"), lambda q, st=st: q.reply(M.key("r1", "engage"), M.encode(st)))
        got: list = []
        t_end = time.monotonic() + 20
        while len(got) < 2 and time.monotonic() < t_end:  # until the router knows both queryables (bounded)
            got = engage.ask(tool, "r1", M.EngageRequest(stamp=0.0), timeout=1.0)
    assert sorted(st.node for st in got) == ["driver", "driver2"]
