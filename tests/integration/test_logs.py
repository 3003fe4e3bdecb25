"""Logs a person can read (findings of a lab's first day): nothing said "lost the router" or "reconnected", and the
driver host logged nothing when it stopped on SIGTERM. A driver host (the emulated CAN learner) and the lab's router
run as processes of their own; the router is stopped and started again on the same port."""

from __future__ import annotations

import os
import signal

import pytest

from bridge.nodes.zsession import free_port, tcp
from bridge.tools.procs import Children, said
from tests.lab import start_router
from tests.wait import until


@pytest.mark.timeout(180)
def test_the_driver_host_says_it_lost_the_router_when_it_is_back_and_that_it_stopped() -> None:
    port = free_port()
    with Children() as kids:
        router = start_router(kids, "--listen", tcp(port))
        host = kids.spawn(["driver", "--link", "can", "--emulate", "--x0", "0,0,0", "--robot", "logs", "--mode",
                           "client", "--connect", tcp(port), "--duration", "150"])
        assert until(lambda: "driver host for logs on link can" in said(host, 20000), 90, 0.2), said(host)
        os.killpg(router.pid, signal.SIGTERM)
        router.wait(timeout=30)
        assert until(lambda: "lost the router at tcp/127.0.0.1" in said(host, 20000), 30, 0.1), said(host)
        start_router(kids, "--listen", tcp(port))
        assert until(lambda: "reconnected to the router at" in said(host, 20000), 60, 0.1), said(host)
        os.killpg(host.pid, signal.SIGTERM)
        host.wait(timeout=30)
        log = said(host, 20000)
    assert "driver host for logs stopped on SIGTERM" in log, log
    back = next(ln for ln in log.splitlines() if "reconnected to the router" in ln)
    assert " after " in back and back.rstrip().endswith(" s"), back
