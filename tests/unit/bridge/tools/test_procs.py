"""Child processes that always go away (:mod:`bridge.tools.procs`): a whole process group stopped by SIGTERM, one
that ignores it killed after the bounded wait, an exited child left alone, a child's log read back, every child of a
:class:`Children` stopped on leaving, and free UDP ports. Readiness is awaited on the child's own line,
never by sleeping. (Every integration test starts its nodes with these.)"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

from bridge.nodes.zsession import free_port, tcp
from bridge.tools.procs import LOG, Children, free_udp_port, said, spawn, stop_group

#: a child that starts a grandchild in its group, says so, and waits; IGNORE makes it ignore SIGTERM
CHILD = """
import os, signal, subprocess, sys, time
if {ignore}:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
g = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
print(g.pid, flush=True)
time.sleep(60)
"""


def _child(ignore: bool) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, "-c", CHILD.format(ignore=ignore)], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    grandchild = int(proc.stdout.readline())  # ready: its grandchild runs
    return proc, grandchild


def _gone(pid: int, timeout: float = 10.0) -> bool:
    """The process ``pid`` (not our child: reaped by its parent or by init) no longer exists."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.02)
    return False


def test_the_whole_group_is_stopped_by_sigterm() -> None:
    proc, grandchild = _child(ignore=False)
    try:
        stop_group(proc, term_timeout=10.0)
        assert proc.returncode == -signal.SIGTERM
        assert _gone(grandchild)  # its grandchild too: the group, not the pid
    finally:
        proc.stdout.close()


def test_a_child_that_ignores_sigterm_is_killed_after_the_bounded_wait() -> None:
    proc, grandchild = _child(ignore=True)
    try:
        t0 = time.monotonic()
        stop_group(proc, term_timeout=0.3)
        assert proc.returncode == -signal.SIGKILL and time.monotonic() - t0 < 6.0
        assert _gone(grandchild)
    finally:
        proc.stdout.close()


def test_a_child_that_has_exited_is_left_alone() -> None:
    proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(4)"], start_new_session=True)
    proc.wait(30)
    stop_group(proc)  # no signal to a group that is gone (its pid may be another's by now)
    assert proc.returncode == 4


def test_spawn_runs_scmbridge_and_said_reads_its_log() -> None:
    proc = spawn(["--version"])
    try:
        assert proc.wait(60) == 0
        text = said(proc)
        assert text.strip() and "\n" in text
        assert said(proc, tail=3) == text[-3:]
    finally:
        proc.log.close()
    assert said(proc) == ""  # a closed log says nothing rather than failing
    other = spawn(["--version"], out=subprocess.DEVNULL)
    assert other.wait(60) == 0 and other.log is None and said(other) == ""


def test_children_run_in_their_own_groups_and_are_all_stopped_on_leaving_their_logs_closed() -> None:
    with Children() as kids:
        a = kids.spawn(["router", "--listen", tcp(free_port()), "--duration", "60"], LOG)
        b = kids.spawn(["--version"])
        assert b.wait(60) == 0
        assert kids.any_exited() and a.poll() is None  # the router runs on
        assert os.getpgid(a.pid) == a.pid != os.getpgid(0)  # in a group of its own: its pid is its group id
        assert "--version ... (exit 0)" in kids.said()
    assert a.returncode is not None and a.log.closed and b.log.closed  # stopped by leaving, not by its duration


def test_free_udp_port_can_be_bound_now() -> None:
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))
