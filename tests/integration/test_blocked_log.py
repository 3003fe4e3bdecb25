"""A node whose log nobody reads keeps its loop: the driver host (``scmbridge driver --link can --emulate``, a real
process) writes its log into a pipe of one page that this test does not read, while a station's commands start and
stop (each start and each deadman stop is a log line). Once the pipe is full, a log line written from the loop would
wait for a reader: the loop would neither echo nor feed its controllers' watchdogs (bridge/core/logsink.py). Real
Zenoh on a free 127.0.0.1 port; the process bounded by --duration and always stopped."""

from __future__ import annotations

import fcntl
import os
import select

import pytest

from bridge.core import wire as M
from bridge.core.wire import Keys
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import spawn, stop_group
from tests.integration.test_driver_host import Listener, _cmd
from tests.wait import Pace

#: fcntl(2): set a pipe's capacity (Linux); one page is its least
F_SETPIPE_SZ = 1031
PAGE = 4096


def _read_all(fd: int, timeout: float) -> bytes:
    """What the pipe holds and gets within ``timeout`` s of quiet."""
    out = b""
    while select.select([fd], [], [], timeout)[0]:
        chunk = os.read(fd, 1 << 16)
        if not chunk:
            break
        out += chunk
    return out


@pytest.mark.timeout(120)
def test_a_driver_host_whose_log_nobody_reads_keeps_echoing_and_feeding_its_controllers(tmp_path) -> None:
    r, w = os.pipe()
    fcntl.fcntl(w, F_SETPIPE_SZ, PAGE)
    port, robot = free_port(), f"blog{os.getpid()}"
    proc = spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", "0,0,0", "--robot", robot,
                  "--listen", tcp(port), "--duration", "60"], out=w)
    os.close(w)
    try:
        with open_session(make_config(connect=[tcp(port)])) as session:
            lis = Listener(session, robot)
            assert lis.wait(lambda s: s.status and s.status[-1].ok, 30), [s.text for s in lis.status[-2:]]
            pub = session.declare_publisher(Keys(robot).cmd)
            seq, logged = 0, 0
            # bursts of commands, each followed by a deadman stop: three log lines a cycle (driving, the deadman,
            # stopped), about 250 bytes; the pipe is full after a dozen cycles at most (its start-up said ~2 KB)
            for _ in range(20):
                pace = Pace(0.05)
                for _ in range(3):
                    seq += 1
                    pub.put(M.encode(_cmd(seq, 0.2, 0.0)))
                    pace.wait()  # pacing: a station's 20 Hz
                with lis.lock:
                    n = len(lis.applied)
                # the deadman stop comes 0.3 s after the burst: counted, not slept, so a loaded machine waits longer
                assert lis.wait(lambda s, n=n: any(a.reason == "deadman" for a in s.applied[n:]), 10), seq
                logged += 1
            # the log is full and still unread: the loop goes on, 50 echoes a second, the controllers fed
            with lis.lock:
                n = len(lis.applied)
            assert lis.wait(lambda s: len(s.applied) - n >= 100, 10), len(lis.applied) - n
            with lis.lock:
                assert lis.status[-1].ok, lis.status[-1].text  # no watchdog trip, no fault
        said = _read_all(r, 2.0)
        assert len(said) > PAGE, len(said)  # the pipe did fill: the test exercised what it says
        assert said.count(b"vehicle stopped: deadman") >= logged - 1, said[-2000:]  # the lines were kept, in order
    finally:
        stop_group(proc)
        os.close(r)
