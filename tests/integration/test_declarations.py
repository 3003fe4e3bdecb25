"""A node keeps what it declares on Zenoh and undeclares it itself (bridge.nodes.zsession.Declared): a fleet robot
whose loop failed lets go of its keys on the process's one session while the others keep theirs, and a driver host
that stops serving leaves no subscriber, queryable or liveliness token behind on a session that stays open. Seen from
a second real session: a publisher's matching status (is anyone subscribed?), a query's answers, a liveliness get.
Free 127.0.0.1 ports, bounded waits, every loop stopped."""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.driver_config import load_driver
from bridge.nodes.driver_host import DriverHost
from bridge.nodes.station import FleetLoop, KernelBuild, Station
from bridge.nodes.zsession import Declared, free_port, make_config, open_session, tcp
from tests.plugins import EXAMPLE
from tests.wait import until

PERIOD = 0.1


def _answers(session: zenoh.Session, key: str) -> int:
    return sum(1 for r in session.get(key, timeout=1.0) if r.ok is not None)


def _alive(session: zenoh.Session, robot: str) -> int:
    return sum(1 for r in session.liveliness().get(M.alive_key(robot, "driver"), timeout=1.0) if r.ok is not None)


class _Handle:
    def __init__(self) -> None:
        self.undeclared = 0

    def undeclare(self) -> None:
        self.undeclared += 1


def test_declared_undeclares_each_once_last_first_and_what_comes_after_at_once() -> None:
    order: list[int] = []
    d = Declared()
    hs = [d.keep(_Handle()) for _ in range(3)]
    for i, h in enumerate(hs):
        h.undeclare = lambda i=i: order.append(i)  # type: ignore[method-assign]
    assert len(d) == 3 and d.undeclare() == 3 and order == [2, 1, 0]
    assert d.undeclare() == 0 and order == [2, 1, 0]  # once
    late = d.keep(_Handle())
    assert late.undeclared == 1 and len(d) == 0  # kept after the end: undeclared at once


@pytest.mark.timeout(90)
def test_a_fleet_robot_whose_loop_failed_undeclares_its_keys_and_the_others_keep_theirs(tmp_path: Path) -> None:
    robots = [f"dcl{os.getpid()}x{k}" for k in range(2)]
    stations = []
    for r in robots:
        st = Station(StationConfig(), r, 1 / PERIOD, tmp_path / f"pairs-{r}.bin", load_mission(None))
        st.build = KernelBuild(None)  # these stations never drive: no MPC code generation
        stations.append(st)
    bad, fail = stations[1], threading.Event()
    real_tick = bad.core.tick

    def failing(inputs, now):
        if fail.is_set():
            raise RuntimeError("injected failure")
        return real_tick(inputs, now)

    bad.core.tick = failing
    port, stop = free_port(), threading.Event()
    fleet = FleetLoop(stations, stop, 60.0, False)
    with open_session(make_config(mode="router", listen=[tcp(port)])) as server:
        for st in stations:
            st.declare(server)
        loop = threading.Thread(target=fleet.run, name="test-fleet", daemon=True)
        loop.start()
        try:
            with open_session(make_config(mode="client", connect=[tcp(port)])) as client:
                missions = {r: client.declare_publisher(M.key(r, "mission")) for r in robots}
                for r in robots:  # both robots subscribe to their missions and answer on their keys
                    assert until(lambda r=r: missions[r].matching_status.matching, 20), r
                    assert until(lambda r=r: _answers(client, M.key(r, "pairs")) == 1, 20), r
                    assert until(lambda r=r: _answers(client, M.status_key(r, "station")) == 1, 20), r
                fail.set()
                assert until(lambda: robots[1] in fleet.failed, 20), fleet.failed
                assert until(lambda: not missions[robots[1]].matching_status.matching, 20)
                assert _answers(client, M.key(robots[1], "pairs")) == 0
                assert _answers(client, M.status_key(robots[1], "station")) == 0
                assert len(bad.inputs.declared) == 0
                # the other robot, on the same session, keeps every key
                assert missions[robots[0]].matching_status.matching
                assert _answers(client, M.key(robots[0], "pairs")) == 1
                assert len(stations[0].inputs.declared) > 0
        finally:
            stop.set()
            loop.join(timeout=10)
        assert not loop.is_alive()


@pytest.mark.timeout(90)
def test_a_driver_host_that_stops_serving_leaves_nothing_declared(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLE))  # the example link package's module: a driver without a device
    import scmbridge_loopback_link as loopback

    robot = f"dclh{os.getpid()}"
    host = DriverHost(load_driver(None), "loopback", loopback.DRIVER(loopback.CONFIG()), robot, 50.0,
                      latch_path=tmp_path / "estop.bin")
    port, stop = free_port(), threading.Event()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as server, \
            open_session(make_config(mode="client", connect=[tcp(port)])) as client:
        serving = threading.Thread(target=host.serve, args=(server, stop, None), name="test-host", daemon=True)
        serving.start()
        try:
            cmd = client.declare_publisher(M.key(robot, "cmd"))
            assert until(lambda: cmd.matching_status.matching, 20)
            assert until(lambda: _alive(client, robot) == 1, 20)
            assert until(lambda: _answers(client, M.status_key(robot, "driver")) == 1, 20)
            assert len(host.inputs.declared) >= 8  # cmd, estop, two queryables, the token, three publishers
        finally:
            stop.set()
            serving.join(timeout=30)
            host.close()
        assert not serving.is_alive()
        # the session the host served on is still open: what it declared is gone because it undeclared it
        assert until(lambda: not cmd.matching_status.matching, 20)
        assert _alive(client, robot) == 0
        assert _answers(client, M.status_key(robot, "driver")) == 0
        assert _answers(client, M.key(robot, "engage")) == 0
        assert len(host.inputs.declared) == 0
    sys.modules.pop("scmbridge_loopback_link", None)
