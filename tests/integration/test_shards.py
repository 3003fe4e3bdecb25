"""Beyond one base station: robots sharded over two station hosts behind one Zenoh router, as a lab lays it out
(deploy/README.md, "Several base stations"). Each host serves its half of the fleet from one process (``station
--shard``, the shard map in the shared config); an operator's ``status --all`` and ``estop --all`` reach every robot;
killing one host stops only its robots (each by its own driver host's deadman) while the other half drives on.

Real processes over real Zenoh on loopback: the router is this test's session on 127.0.0.1, the two station hosts
listen on 127.0.0.2 and 127.0.0.3 of their own, four driver hosts run the emulated CAN link."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, said
from tests.collect import Collector


def _cli(port: int, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args, "--mode", "client", "--connect", tcp(port)],
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.timeout(240)
def test_two_station_hosts_each_serve_half_the_fleet_and_one_dying_stops_only_its_robots(tmp_path) -> None:
    tag = f"s{os.getpid()}"
    shards = {"hostA": [f"{tag}a1", f"{tag}a2"], "hostB": [f"{tag}b1", f"{tag}b2"]}
    robots = [r for rs in shards.values() for r in rs]
    cfg = tmp_path / "fleet.toml"
    cfg.write_text("[fleet.shards]\n" + "".join(f'{h} = [{", ".join(repr(r) for r in rs)}]\n'.replace("'", '"')
                                                for h, rs in shards.items()))
    port = free_port()
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        station = {r: col.listen(M.status_key(r, "station"), M.Status) for r in robots}
        applied = {r: col.listen(M.key(r, "applied"), M.Applied) for r in robots}
        drivers = {r: kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, "--robot", r,
                                  "--mode", "client", "--connect", tcp(port), "--duration", "200"]) for r in robots}
        hosts = {h: kids.spawn(["station", "--config", str(cfg), "--shard", h, "--start", "--mode", "client",
                                "--connect", tcp(port), "--listen", tcp(free_port(), f"127.0.0.{2 + i}"),
                                "--duration", "180"]) for i, h in enumerate(shards)}

        def driving(rs: list[str]) -> bool:
            return all(station[r] and station[r][-1].text == "driving" for r in rs)

        def hosts_said() -> str:  # the station hosts, and the driver host of each robot not driving
            return ("".join(f"\n--- {h} (exit {hosts[h].poll()}):\n" + said(hosts[h], 1500) for h in shards)
                    + "".join(f"\n--- driver {r} (exit {drivers[r].poll()}):\n" + said(drivers[r], 2500)
                              for r in robots if not driving([r])))

        assert col.wait(lambda: driving(robots), 120), (
            str({r: station[r][-1].text if station[r] else None for r in robots}) + hosts_said())
        every = _cli(port, "status", "--all")
        assert every.returncode == 0, every.stderr
        rows = {tuple(line.split()[:3]) for line in every.stdout.splitlines() if line.strip()}
        for r in robots:
            # the driver host's line says what the vehicle does, measured (it may be between two commands' effect)
            drv = [ln for ln in every.stdout.splitlines() if ln.split()[:2] == [r, "driver"]]
            assert (r, "station", "driving") in rows and len(drv) == 1, every.stdout
            assert drv[0].split()[2] in ("moving", "stopped") and "| engaged |" in drv[0], every.stdout

        # host A dies without a word: its robots stop by their deadman, host B's keep driving
        os.killpg(hosts["hostA"].pid, signal.SIGKILL)
        hosts["hostA"].wait(10)
        t_kill = time.monotonic()

        def stopped(r: str) -> bool:
            return bool(applied[r]) and applied[r][-1].reason == "deadman" and applied[r][-1].v == 0.0

        assert col.wait(lambda: all(stopped(r) for r in shards["hostA"]), 10), {
            r: applied[r][-1] if applied[r] else None for r in shards["hostA"]}
        assert time.monotonic() - t_kill < 10
        with col.lock:
            n_before = {r: len(applied[r]) for r in shards["hostB"]}
        # a second of host B's robots' echoes (50 Hz each): counted, not slept, so a loaded machine gives it longer
        assert col.wait(lambda: all(len(applied[r]) - n_before[r] >= 50 for r in shards["hostB"]), 30), {
            r: len(applied[r]) - n_before[r] for r in shards["hostB"]}
        with col.lock:
            for r in shards["hostB"]:
                later = applied[r][n_before[r]:]
                assert station[r][-1].text == "driving", station[r][-1].text
                # driving on: its host's commands keep arriving and moving it (on a starved machine a late one may
                # still run into the deadman for a moment: the driver host's own safety, not the other host's death)
                moving = [a for a in later if a.reason in ("cmd", "clamped") and a.v != 0.0]
                assert len(moving) >= 0.5 * len(later) > 0, [a.reason for a in later]

        # one operator command reaches every robot, the orphaned half included
        stop = _cli(port, "estop", "--all", "--timeout", "10")
        assert stop.returncode == 0, (stop.stdout, stop.stderr)
        for r in robots:
            assert f"{r}/driver-can: LATCHED by operator" in stop.stdout, stop.stdout
        assert col.wait(lambda: all(applied[r] and applied[r][-1].reason == "estop" for r in shards["hostB"]), 5)


@pytest.mark.timeout(90)
def test_one_robot_that_cannot_be_served_leaves_the_others_of_its_process_running(tmp_path) -> None:
    """``station --robots``: a robot whose station cannot be built (here its pair store path is a directory) is
    named in the log and left stopped; the process serves the others and exits non-zero at the end."""
    from bridge.core.paths import state_dir

    tag = f"f{os.getpid()}"
    good, bad = f"{tag}ok", f"{tag}bad"
    (state_dir() / f"pairs-{bad}.bin").mkdir(parents=True)
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        seen = {r: col.listen(M.status_key(r, "station"), M.Status) for r in (good, bad)}
        proc = kids.spawn(["station", "--robots", f"{good},{bad}", "--mode", "client", "--connect", tcp(port),
                           "--duration", "6"], out=subprocess.PIPE, text=True)
        assert col.wait(lambda: bool(seen[good]), 60), "the good robot's station never spoke"
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert not seen[bad]
    assert f"{bad}: not served" in out and "is a directory" in out, out
