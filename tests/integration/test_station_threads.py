"""A many-robot station process holds no thread per robot for its Zenoh callbacks: they run on Zenoh's own thread
(``bridge.nodes.node.on_zenoh``), and what must not run there (a mission built from its message, a query answered
while no loop runs) on one thread of the process (``OffThread``). Declaring a dozen robots' keys adds a bounded
handful of threads, not several per robot, and every callback still does its work: a driver host's status and a
mission reach the robot's inbox, a malformed sample and a malformed request are counted and dropped, a query is
answered, the status key answers; undeclared, nothing answers (docs/ARCHITECTURE.md, "Threads and clocks").
Real Zenoh sessions on a free 127.0.0.1 port, bounded waits."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import zenoh

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.mission_control import spec_of
from bridge.nodes.station import KernelBuild, Station
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from tests.wait import until

ROBOTS = 12
#: threads the declarations may add whatever the number of robots: the off-Zenoh thread, and Zenoh's own pools
#: growing by a thread or two (a thread per callback would be eight per robot)
MORE_AT_MOST = 4


def _threads() -> int:
    """The process's threads as the kernel counts them (every one, Python's or Zenoh's)."""
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("Threads:"))


def _answers(session: zenoh.Session, key: str, payload: bytes | None = None) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(key, payload=payload, timeout=2.0) if r.ok is not None]


def _holds(st: Station, pred) -> bool:
    with st.rx.lock:
        return bool(pred(st.rx.inbox))


@pytest.mark.timeout(90)
def test_a_dozen_robots_callbacks_add_no_thread_per_robot_and_each_still_does_its_work(tmp_path: Path) -> None:
    robots = [f"thr{os.getpid()}x{k}" for k in range(ROBOTS)]
    stations = []
    for r in robots:
        st = Station(StationConfig(), r, 10.0, tmp_path / f"pairs-{r}.bin", load_mission(None))
        st.build = KernelBuild(None)  # these stations never drive: no MPC code generation
        stations.append(st)
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as server, \
            open_session(make_config(mode="client", connect=[tcp(port)])) as client:
        before = _threads()
        for st in stations:
            st.declare(server)
        assert _threads() - before <= MORE_AT_MOST, (before, _threads())
        try:
            spec = spec_of(load_mission(None))
            for r, st in zip(robots, stations):
                status = M.Status(stamp=1.0, seq=1, node="driver", ok=True, text="link loopback: driving (cmd)")
                client.put(M.status_key(r, "driver"), M.encode(status))
                client.put(M.status_key(r, "driver"), b"\xff not a status")
                client.put(M.key(r, "mission"), M.encode(spec))
                assert until(lambda st=st: _holds(st, lambda box: box.driver is not None
                                                  and box.mission is not None), 20), r
                assert until(lambda st=st: st.inputs.snapshot().get("malformed_driver_status") == 1, 20), r
                assert _holds(st, lambda box, status=status: box.driver[0] == status
                              and box.mission[0].name == spec.name)
                # no loop runs: the queries are answered at once (off Zenoh's thread)
                assert len(_answers(client, M.key(r, "pairs"))) == 1, r
                [bad] = _answers(client, M.key(r, "control"), b"\x00 not a request")
                assert "malformed request" in M.decode(bad, M.MissionState).text
                assert st.inputs.snapshot().get("malformed_control") == 1
                # the status key answers with the last status put (on Zenoh's thread)
                st.pubs["status"].put(M.encode(M.Status(stamp=1.0, seq=1, node="station", ok=True, text="idle")))
                [said] = _answers(client, M.status_key(r, "station"))
                assert M.decode(said, M.Status).text == "idle"
            assert _threads() - before <= MORE_AT_MOST, (before, _threads())
        finally:
            for st in stations:
                st.undeclare()
        assert _answers(client, M.key(robots[0], "pairs")) == []
        assert _answers(client, M.status_key(robots[-1], "station")) == []
