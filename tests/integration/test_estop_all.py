"""``scmbridge estop --all`` over real Zenoh against two driver host processes: a robot whose host is stalled is
still found (its liveliness token), tried again until it confirms, and named with a non-zero exit if it never does.

Finding this answers: `estop --all` exited 0 having listed 1 of 2 robots while the other's host was paused 3 s, and
the missed robot received 240 non-zero commands when it came back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.estop import latch_states
from bridge.tools.procs import Children


def _estop(port: int, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bridge", "estop", *args, "--mode", "client", "--connect",
                             tcp(port)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_hosts(session, robots: list[str], timeout: float) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if all(latch_states(session, M.key(r, "estop"), 0.5) for r in robots):
            return
        time.sleep(0.2)
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
    time.sleep(3.0)  # the host is stalled for 3 s while the command runs (the finding's case)
    os.killpg(procs[1].pid, signal.SIGCONT)
    out, err = res.communicate(timeout=30)
    assert res.returncode == 0, (out, err)
    assert f"{a}/driver-can: LATCHED by operator" in out and f"{b}/driver-can: LATCHED by operator" in out
    assert all(st.latched for st in latch_states(session, M.key(b, "estop"), 1.0).values())
