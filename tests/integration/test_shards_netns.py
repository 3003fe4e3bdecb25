"""Two station hosts in two network namespaces of their own behind one Zenoh router (docs/FLEET.md, "several base
stations"): each host reaches the router only over its own link (bench/netns.py), serves its half of the fleet
(``station --shard``), and an operator's ``status --all`` and ``estop --all`` at the router reach every robot of both.

Real processes over real Zenoh: the router is this test's session, listening on 127.0.0.1 (the driver hosts and the
operator's commands) and on each host's private link; four driver hosts run the emulated CAN link. Skipped, with the
reason, where network namespaces cannot be made (not root, no ``ip``)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bench import netns
from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, said
from tests.collect import Collector

WHY_NOT = netns.unavailable()


def _cli(port: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args, "--mode", "client", "--connect", tcp(port)],
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.skipif(bool(WHY_NOT), reason=f"network namespaces cannot be made here: {WHY_NOT}")
@pytest.mark.timeout(240)
def test_two_station_hosts_in_namespaces_of_their_own_are_reached_by_status_all_and_estop_all(tmp_path) -> None:
    tag = f"n{os.getpid() % 100000}"
    shards = {"hostA": [f"{tag}a1", f"{tag}a2"], "hostB": [f"{tag}b1", f"{tag}b2"]}
    robots = [r for rs in shards.values() for r in rs]
    cfg = tmp_path / "fleet.toml"
    cfg.write_text("[fleet.shards]\n" + "".join(f'{h} = [{", ".join(chr(34) + r + chr(34) for r in rs)}]\n'
                                                for h, rs in shards.items()))
    port = free_port()
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    with netns.hosts(2, tag) as hosts:
        listen = [tcp(port), *(tcp(port, h.router_addr) for h in hosts)]
        with open_session(make_config(mode="router", listen=listen)) as session, Children() as kids:
            col = Collector(session)
            station = {r: col.listen(M.status_key(r, "station"), M.Status) for r in robots}
            # each driver host's output kept (a temporary file): a robot that does not drive says why in the failure
            drivers = {r: kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, "--robot", r,
                                      "--mode", "client", "--connect", tcp(port), "--duration", "200"])
                       for r in robots}
            procs = {h: kids.spawn(["station", "--config", str(cfg), "--shard", h, "--start", "--mode", "client",
                                    "--connect", tcp(port, host.router_addr), "--duration", "180"],
                                   prefix=host.prefix, env=dict(os.environ, SCMBRIDGE_STATE_DIR=str(tmp_path / h)))
                     for h, host in zip(shards, hosts)}

            def hosts_said() -> str:
                return ("".join(f"\n--- {h} (exit {procs[h].poll()}):\n" + said(procs[h], 1500) for h in shards)
                        + "".join(f"\n--- driver host {r} (exit {d.poll()}):\n" + said(d, 1500)
                                  for r, d in drivers.items() if not (station[r] and station[r][-1].text == "driving")))

            assert col.wait(lambda: all(station[r] and station[r][-1].text == "driving" for r in robots), 120), (
                str({r: station[r][-1].text if station[r] else None for r in robots}) + hosts_said())
            for p in procs.values():  # each host really has a network of its own
                assert not netns.same_namespace(p.pid)

            every = _cli(port, "status", "--all")
            assert every.returncode == 0, every.stderr
            rows = {tuple(line.split()[:3]) for line in every.stdout.splitlines() if line.strip()}
            for r in robots:
                assert (r, "station", "driving") in rows, every.stdout

            stop = _cli(port, "estop", "--all", "--timeout", "10")
            assert stop.returncode == 0, (stop.stdout, stop.stderr)
            for r in robots:
                assert f"{r}/driver-can: LATCHED by operator" in stop.stdout, stop.stdout
            # every station, on either host, hears its robot stopped (its driver host's status: estop latched)
            assert col.wait(lambda: all(station[r][-1].text != "driving" for r in robots), 10), (
                {r: station[r][-1].text for r in robots})
