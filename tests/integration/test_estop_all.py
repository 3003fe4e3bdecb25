"""``scmbridge estop --all`` over real Zenoh against two driver host processes: a robot whose host is stalled is
still found (its liveliness token), tried again until it confirms, and named with a non-zero exit if it never does.

Finding this answers: `estop --all` exited 0 having listed 1 of 2 robots while the other's host was paused 3 s, and
the missed robot received 240 non-zero commands when it came back."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.estop import latch_states
from bridge.tools.procs import Children
from tests.wait import until


def _estop(port: int, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bridge", "estop", *args, "--mode", "client", "--connect",
                             tcp(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


class _TokensSeen:
    """The fake robots' liveliness tokens the router has told ``session`` of (a liveliness subscriber declared
    before them: a callback, never a blocking query, which could hang the test with thousands of tokens)."""

    def __init__(self, session) -> None:
        self.names: set[str] = set()
        self.lock = threading.Lock()
        self.sub = session.liveliness().declare_subscriber(f"{M.PREFIX}/*/alive/**", self._on)

    def _on(self, sample) -> None:
        name = str(sample.key_expr).split("/")[1]
        if name.startswith("fake"):
            with self.lock:
                if sample.kind == zenoh.SampleKind.DELETE:  # a token undeclared
                    self.names.discard(name)
                else:
                    self.names.add(name)

    def wait(self, n: int, timeout: float = 30.0) -> bool:
        """Whether at least ``n`` fake tokens were seen within ``timeout``."""
        def enough() -> bool:
            with self.lock:
                return len(self.names) >= n

        return bool(until(enough, timeout, 0.1))


def _wait_hosts(session, robots: list[str], timeout: float) -> None:
    if not until(lambda: all(latch_states(session, M.key(r, "estop"), 0.5) for r in robots), timeout, 0.2):
        pytest.fail(f"driver hosts {robots} did not come up in {timeout} s")


@pytest.fixture
def two_hosts():
    port = free_port()
    tag = f"e{os.getpid()}"
    robots = [f"{tag}a", f"{tag}b"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        procs = [kids.spawn(["driver", "--link", "can", "--emulate", "--robot", r, "--mode", "client", "--connect",
                             tcp(port), "--duration", "60"], out=subprocess.DEVNULL) for r in robots]
        _wait_hosts(session, robots, 30.0)
        try:
            yield port, session, robots, procs
        finally:
            for p in procs:
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGCONT)


def test_estop_all_names_a_stalled_robot_and_exits_non_zero(two_hosts) -> None:
    port, session, (a, b), procs = two_hosts
    os.killpg(procs[1].pid, signal.SIGSTOP)
    res = _estop(port, "--all", "--timeout", "2")
    out, err = res.communicate(timeout=30)
    assert res.returncode == 1, (out, err)
    assert f"{a}/driver-can: LATCHED by operator" in out
    assert f"not confirmed by {b}" in err, err


def test_estop_all_retries_a_stalled_robot_until_it_confirms(two_hosts) -> None:
    port, session, (a, b), procs = two_hosts
    os.killpg(procs[1].pid, signal.SIGSTOP)
    res = _estop(port, "--all", "--timeout", "8")
    time.sleep(3.0)  # a simulated stall: the host is stalled for 3 s while the command runs (the finding's case)
    os.killpg(procs[1].pid, signal.SIGCONT)
    out, err = res.communicate(timeout=30)
    assert res.returncode == 0, (out, err)
    assert f"{a}/driver-can: LATCHED by operator" in out and f"{b}/driver-can: LATCHED by operator" in out, err
    assert all(st.latched for st in latch_states(session, M.key(b, "estop"), 1.0).values())


def _counted(err: str, what: str, n: int) -> None:
    """``err`` counts ``n`` of ``what``, or, where it says the network was still listing its liveliness tokens when
    the discovery window ended (a loaded machine: the tool's window is bounded, the count is then a lower bound),
    between 1 and ``n``."""
    m = re.search(rf"(\d+) {re.escape(what)}", err)
    assert m, err
    if "still listing its liveliness tokens" in err:
        assert 0 < int(m.group(1)) <= n, err
    else:
        assert int(m.group(1)) == n, err


def test_estop_all_among_fake_liveliness_tokens_names_the_fleets_silent_robot_in_bounded_output(two_hosts,
                                                                                                tmp_path) -> None:
    """Finding: with 2000 liveliness tokens declared by another client, `estop --all` sent each robot's estop one
    after another (the real robot's first stop 1.61 s after the start), printed about 2000 lines and ran 7.5-16 s;
    a robot on a router not connected was never named. With the lab's fleet list the missing robot is named and
    fails the exit status, the fake names are counted in one line, and the output stays short. (How soon the
    first stop comes is measured by ``scmbridge bench attack``, not here.)"""
    port, session, (a, b), procs = two_hosts
    fleet = tmp_path / "fleet.toml"
    fleet.write_text(f'[fleet]\nrobots = ["{a}", "{b}", "gone1"]\n')
    seen = _TokensSeen(session)
    with open_session(make_config(mode="client", connect=[tcp(port)])) as faker:
        tokens = [faker.liveliness().declare_token(M.alive_key(f"fake{i}", "driver")) for i in range(2000)]
        try:
            assert seen.wait(2000), f"the router learned {len(seen.names)} of the 2000 fake tokens"
            # the deadline for the two real hosts' confirmations (gone1 never answers, so it is always spent): 2 s
            # ran out beside busy loops with 2000 tokens on the router
            res = _estop(port, "--all", "--fleet", str(fleet), "--timeout", "6")
            out, err = res.communicate(timeout=60)
        finally:
            for t in tokens:
                t.undeclare()
            seen.sub.undeclare()
    assert res.returncode == 1, (out, err)
    assert f"{a}/driver-can: LATCHED by operator" in out and f"{b}/driver-can: LATCHED by operator" in out, err
    assert "not confirmed by gone1" in err and "fake" not in err.split("not confirmed by")[1], err
    _counted(err, "name(s) seen on the network, not in the fleet list", 2000)
    assert len((out + err).splitlines()) < 12, out + err
    # without the fleet file every name must answer: the fake ones fail it, in bounded output too
    seen = _TokensSeen(session)
    with open_session(make_config(mode="client", connect=[tcp(port)])) as faker:
        tokens = [faker.liveliness().declare_token(M.alive_key(f"fake{i}", "driver")) for i in range(50)]
        try:
            assert seen.wait(50), f"the router learned {len(seen.names)} of the 50 fake tokens"
            res = _estop(port, "--all", "--timeout", "1")
            out, err = res.communicate(timeout=60)
        finally:
            for t in tokens:
                t.undeclare()
            seen.sub.undeclare()
    assert res.returncode == 1 and len((out + err).splitlines()) < 12, out + err
    _counted(err, "more", 38)  # the 50 silent names: 12 shown, the rest counted
