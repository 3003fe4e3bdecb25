"""One thread ticks every robot of a many-robot station process (``station --robots``: ``FleetLoop``), each on its own
deadlines at its own phase of the period, its missed deadlines counted as a loop of its own counts them
(``Deadlines``: ``FixedRate``'s rules); a robot whose tick fails stops alone; queries are answered between two
ticks; a station no longer hears its own commands back (docs/FLEET.md). Real Stations on a real Zenoh session, free
127.0.0.1 ports, bounded, the loop always stopped."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.fleet_loop import FleetLoop
from bridge.nodes.station import KernelBuild, Station
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.mission import ask
from tests.collect import Collector

PERIOD = 0.1


def _station(tmp_path: Path, robot: str) -> Station:
    st = Station(StationConfig(), robot, 1 / PERIOD, tmp_path / f"pairs-{robot}.bin", load_mission(None))
    st.build = KernelBuild(None)  # these stations never drive: no MPC code generation
    return st


def _phase(stamps: list[float]) -> float:
    """The median phase of ``stamps`` in the period, wrap-safe: each read against the first's phase."""
    t = np.asarray(stamps)
    ref = t[0] % PERIOD
    return float((ref + np.median((t - ref + PERIOD / 2) % PERIOD - PERIOD / 2)) % PERIOD)


@pytest.mark.timeout(90)
@pytest.mark.parametrize("threads", [1, 2])
def test_one_thread_ticks_every_robot_at_its_phase_and_a_failing_robot_stops_alone(tmp_path, threads) -> None:
    """With ``threads`` 2 the robots are dealt to two loop threads in phase order; every rule holds the same."""
    robots = [f"fl{os.getpid()}x{k}t{threads}" for k in range(3)]
    stations = [_station(tmp_path, r) for r in robots]
    bad = stations[1]
    calls = {"bad": 0, "own_cmd": 0}
    real_tick = bad.core.tick

    def failing(inputs, now):
        calls["bad"] += 1
        if calls["bad"] >= 5:
            raise RuntimeError("injected failure")
        return real_tick(inputs, now)

    bad.core.tick = failing
    first = stations[0]
    real_on_own = first.rx.on_own_cmd

    def counting(cmd, now):  # what reaches the callback on robot 0's cmd key (its own commands must not)
        calls["own_cmd"] += 1
        real_on_own(cmd, now)

    first.rx.on_own_cmd = counting
    port, stop = free_port(), threading.Event()
    fleet = FleetLoop(stations, stop, 30.0, False, threads=threads)
    with open_session(make_config(mode="router", listen=[tcp(port)])) as server:
        for st in stations:
            st.declare(server)
        loop = threading.Thread(target=fleet.run, name="test-fleet", daemon=True)
        loop.start()
        try:
            with open_session(make_config(mode="client", connect=[tcp(port)])) as client:
                col = Collector(client)
                cmds = {r: col.listen(M.key(r, "cmd"), M.Command) for r in robots}
                status = col.listen(M.status_key(robots[2], "station"), M.Status)
                times = {r: col.times[M.key(r, "cmd")] for r in robots}
                assert col.wait(lambda: all(len(times[r]) >= 20 for r in (robots[0], robots[2])), 20), (
                    {r: len(times[r]) for r in robots})
                # a query is answered between two ticks, at once
                t = time.monotonic()
                ans = ask(client, robots[0], M.MissionRequest(stamp=t, action="status", source="test"), timeout=5.0)
                assert ans is not None and time.monotonic() - t < 1.0
                # another sender's command on robot 2's key is heard (and said), the station's own are not
                client.put(M.key(robots[2], "cmd"), M.encode(M.Command(stamp=1.0, seq=1, v=0.0, omega=0.0,
                                                                        method="stop", epoch=12345)))
                assert col.wait(lambda: any(s.counters.get("foreign_commands", 0) >= 1 for s in status), 5)
                with col.lock:
                    snap = {r: list(times[r]) for r in robots}
                    stamps = {r: [c.stamp for c in cmds[r]] for r in robots}
        finally:
            stop.set()
            loop.join(timeout=10)
        assert not loop.is_alive()
    assert fleet.failed == [robots[1]]
    assert calls["bad"] == 5  # its four good ticks, the failing one, and never again
    # no command after its failure (its first ones may go out before this test's subscriber is connected: the loop
    # starts ticking before the client session is open, so the count is at most four, not exactly four)
    assert len(snap[robots[1]]) <= 4
    assert calls["own_cmd"] == 0 and stations[0].core.counters.foreign_commands == 0
    # each robot on its own phase: the three robots' ticks come a third of a period apart (read on the commands'
    # stamps, the tick's own time, not on their receipt here, which a loaded machine's delivery delays apart)
    phase = {r: _phase(stamps[r][5:]) for r in (robots[0], robots[2])}
    gap = (phase[robots[2]] - phase[robots[0]]) % PERIOD
    assert abs(gap - 2 * PERIOD / 3) < 0.02, gap
    for st in stations:
        assert not st.rx.looping
        st.persist()
