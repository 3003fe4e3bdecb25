"""A lab's own link, installed as a package of its own (deploy/examples/link-plugin, registered in the
``scmbridge.links`` entry-point group), is accepted by a real driver host: ``scmbridge driver --link loopback``
builds it from its ``[link.loopback]`` section, opens it, publishes its poses on a real Zenoh session and stops
on SIGTERM like any link."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path

import pytest
import zenoh

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, said
from tests.plugins import ROOT, install_example


@pytest.mark.timeout(90)
def test_the_driver_host_runs_a_link_installed_as_a_package(tmp_path: Path) -> None:
    site = install_example(tmp_path / "site")
    (tmp_path / "driver.toml").write_text('robot = "pt"\n[link.loopback]\nstart_x = 2.5\n')
    port = free_port()
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{site}")
    states: list[M.LearnerState] = []
    got = threading.Event()

    def on_state(sample: zenoh.Sample) -> None:
        states.append(M.decode(sample.payload.to_bytes(), M.LearnerState))
        got.set()

    with Children() as kids:
        host = kids.spawn(["driver", "--link", "loopback", "--config", str(tmp_path / "driver.toml"), "--listen",
                           tcp(port), "--duration", "60"], env=env)
        with open_session(make_config(connect=[tcp(port)], mode="peer")) as session:
            sub = session.declare_subscriber(M.key("pt", "state"), on_state)
            try:
                assert got.wait(45), said(host)
            finally:
                sub.undeclare()
        os.killpg(host.pid, signal.SIGTERM)
        assert host.wait(timeout=30) == 0, said(host)
        log = said(host, 20000)
    assert "driver host for pt on link loopback" in log, log
    assert "driver host for pt stopped on SIGTERM" in log, log
    assert states[0].x == pytest.approx(2.5)  # the package's driver, built from its own [link.loopback] section
