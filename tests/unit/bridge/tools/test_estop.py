"""``scmbridge estop`` (:mod:`bridge.tools.estop`): its arguments, and :func:`latch_states` and :func:`confirm` on one
real Zenoh session whose own queryable answers as a driver host would: each answer keyed by robot and node, what
does not decode skipped, an estop sent again at each try until the asked state is confirmed or the deadline passes.
The command end to end against real driver hosts (one, several, ``--all``, releases refused) is in
tests/integration/test_estop_all.py, tests/integration/test_driver_host.py and tests/integration/test_acts.py."""

from __future__ import annotations

import argparse
import threading
import time

import pytest
import zenoh

from bridge.core import wire as M
from bridge.nodes.zsession import make_config
from bridge.tools import estop


def _args(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    estop.arguments(ap)
    return ap.parse_args(list(argv))


def test_the_arguments_name_one_robot_some_or_all_and_default_to_latching() -> None:
    a = _args("--robot", "rover1")
    assert (a.robot, a.robots, a.all, a.release, a.source, a.reason, a.timeout) == (
        "rover1", None, False, False, "operator", "", 5.0)
    assert _args("--robots", "a,b", "--release", "--source", "safety").robots == ["a", "b"]
    assert _args("--all").all
    for argv in ([], ["--robot", "a", "--all"], ["--robots", "a,a"], ["--robot", "a", "--timeout", "0"]):
        with pytest.raises(SystemExit):
            _args(*argv)


class Host:
    """A driver host's estop queryable and subscriber on ``robot`` in the test's session: latches on what it
    receives (from the second message on, if ``slow``) and answers queries with its latch."""

    def __init__(self, session: zenoh.Session, robot: str, slow: bool = False) -> None:
        self.robot, self.slow = robot, slow
        self.received: list[M.Estop] = []
        self.latched = False
        self.lock = threading.Lock()
        session.declare_subscriber(M.key(robot, "estop"), self.on_estop)
        session.declare_queryable(M.key(robot, "estop"), self.on_query)

    def on_estop(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.received.append(M.decode(sample.payload.to_bytes(), M.Estop))
            if len(self.received) >= (2 if self.slow else 1):
                self.latched = self.received[-1].engaged

    def on_query(self, q: zenoh.Query) -> None:
        with self.lock:
            st = M.EstopState(stamp=1.0, node="driver", latched=self.latched, source="operator")
        q.reply(M.key(self.robot, "estop"), M.encode(st))


def _broken(q: zenoh.Query) -> None:
    """A host whose answer does not decode (on a key of its own: Zenoh keeps one reply per key)."""
    q.reply("scm/broken/estop", b"\xc1")


def test_latch_states_are_keyed_by_robot_and_node() -> None:
    with zenoh.open(make_config()) as s:
        Host(s, "a")
        Host(s, "b")
        s.declare_queryable("scm/broken/estop", _broken)
        got = estop.latch_states(s, "scm/*/estop", 2.0)
        assert estop.latch_states(s, "scm/nobody/estop", 0.2) == {}
    assert set(got) == {"a/driver", "b/driver"} and not any(st.latched for st in got.values())


def test_confirm_sends_again_at_each_try_until_the_asked_state_is_confirmed() -> None:
    nonces = iter(range(1000))

    def msg(to) -> M.Estop:  # a stop needs no address (None)
        assert to is None
        return M.Estop(stamp=time.monotonic(), engaged=True, source="operator", nonce=f"n{next(nonces)}")

    with zenoh.open(make_config()) as s:
        slow, quick = Host(s, "slow", slow=True), Host(s, "quick")
        answers = estop.confirm(s, ["slow", "quick", "gone"], msg, True, time.monotonic() + 1.5)
    assert answers["slow"]["slow/driver"].latched and answers["quick"]["quick/driver"].latched
    assert answers["gone"] == {}  # nobody answered it: the tool names it
    assert len(slow.received) >= 2 and len({m.nonce for m in slow.received}) == len(slow.received)  # sent again
    assert len(quick.received) <= len(slow.received)  # a confirmed robot is not sent to again


def test_two_driver_hosts_of_one_robot_are_each_heard() -> None:
    """Finding (this file): both hosts answer on ``scm/<robot>/estop``, and Zenoh's default reply consolidation kept
    one reply per key, so the tool saw (and confirmed) one host only. Clients of one router on loopback, as a lab."""
    from bridge.nodes.zsession import free_port, tcp

    port = free_port()
    client = make_config(mode="client", connect=[tcp(port)])
    with zenoh.open(make_config(mode="router", listen=[tcp(port)])) as _router, \
            zenoh.open(client) as h1, zenoh.open(client) as h2, zenoh.open(client) as tool:
        for s, node, latched in ((h1, "driver", True), (h2, "driver2", False)):
            st = M.EstopState(stamp=1.0, node=node, latched=latched)
            s.declare_queryable(M.key("r1", "estop"), lambda q, st=st: q.reply(M.key("r1", "estop"), M.encode(st)))
        got: dict = {}
        t_end = time.monotonic() + 20
        while len(got) < 2 and time.monotonic() < t_end:  # until the router knows both queryables (bounded)
            got = estop.latch_states(tool, M.key("r1", "estop"), 1.0)
    assert {k: st.latched for k, st in got.items()} == {"r1/driver": True, "r1/driver2": False}


def test_known_robots_finds_the_liveliness_tokens_and_says_when_the_list_was_complete() -> None:
    with zenoh.open(make_config()) as s:
        tokens = [s.liveliness().declare_token(M.alive_key(f"r{i}", "driver")) for i in range(5)]
        Host(s, "answering")
        robots, complete = estop.known_robots(s, 1.0)
        for t in tokens:
            t.undeclare()
    assert robots == {"answering", "r0", "r1", "r2", "r3", "r4"}
    assert complete  # five tokens in one session: the query ends on its last answer, long before its bound


def test_a_cut_discovery_is_said_and_its_count_is_a_lower_bound(capsys) -> None:
    args = _args("--all", "--timeout", "1")
    for complete in (True, False):
        code = estop.report(args, None, ["a"], ["fake1", "fake2"], {"a": {}}, True, complete)
        err = capsys.readouterr().err
        assert code == 1 and "not confirmed by a" in err
        assert ("still listing its liveliness tokens" in err) is not complete
        assert ("at least 2 name(s) seen" if not complete else "\n2 name(s) seen") in "\n" + err, err
