"""Faults the station and the driver host must survive or stop on: stale telemetry (at both ends), a full disk
under the pair store, a driver host killed while the robot drives (the robot's own watchdog stops it)."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.sources import Why
from bridge.nodes.station_core import StationCore
from bridge.nodes.station_fitness import why_not_drive
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, free_udp_port
from sim_learner.dynamics import mpc_learner
from sim_learner.udp_robot import UdpRobot
from sim_learner.vehicle import SimVehicle
from tests.collect import Collector
from tests.wait import Pace, until


def _status(ok: bool = True, text: str = "link can: driving (cmd)") -> M.Status:
    return M.Status(stamp=1.0, seq=1, node="driver", ok=ok, text=text)


def test_the_station_drives_only_a_fit_robot_from_a_fresh_pose(tmp_path) -> None:
    """Finding: the station planned from the last pose whatever its age. It now stops and says why."""
    age = StationConfig().station.max_pose_age_s  # what a StationCore judges the pose by (0.5 s)
    pose = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=0.0, theta=0.0)
    assert why_not_drive(10.0, pose, 9.9, _status(), 9.5, age) is None
    assert why_not_drive(10.0, pose, 9.2, _status(), 9.5, age) == Why("no pose for 0.8 s", "no_telemetry")
    assert why_not_drive(10.0, None, -np.inf, _status(), 9.5, age) == Why("no pose yet", "no_telemetry")
    why = why_not_drive(10.0, pose, 9.9, _status(False, "link mavlink: operator took control: mode HOLD"), 9.5, age)
    assert why == Why("robot not ready: link mavlink: operator took control: mode HOLD", "robot_not_ready")
    late = why_not_drive(10.0, pose, 9.9, _status(), 5.0, age)
    assert late.text.startswith("robot not ready: no driver host status") and late.reason == "robot_not_ready"


def test_a_full_disk_is_reported_retried_and_leaves_no_temporary_file(tmp_path, monkeypatch) -> None:
    """Finding: OSError on persist killed the station in a restart loop and left .tmp files."""
    st = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", load_mission())
    real_fsync = os.fsync

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    st.saves.persist()  # no exception: the loop goes on
    assert st.counters.persist_failures == 1 and "No space left on device" in st.saves.error
    assert not list(tmp_path.glob(".*.tmp")) and not (tmp_path / "p.bin").exists()
    status = st.status(1.0)
    assert not status.ok and "pair store not saved" in status.text
    monkeypatch.setattr(os, "fsync", real_fsync)
    st.saves.persist()  # the next period: saved
    assert st.saves.error == "" and (tmp_path / "p.bin").exists()


@pytest.mark.timeout(90)
def test_stale_telemetry_stops_the_robot_and_a_killed_driver_host_leaves_it_to_its_own_watchdog(tmp_path) -> None:
    """Findings: with stale telemetry the driver host kept applying commands (the robot drove blind); and the
    robot must stop by itself when its driver host dies (kill -9), within its watchdog."""
    port, robot = free_port(), f"ft{os.getpid()}"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    bind = free_udp_port()
    with UdpRobot(vehicle, peer=("127.0.0.1", bind), watchdog=0.5) as dev, \
            open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        cfg = tmp_path / "driver.toml"
        cfg.write_text(f"[link.udp]\ninsecure = true\nrobot_port = {dev.port}\nbind_port = {bind}\n")
        k, col = M.Keys(robot), Collector(session)
        applied, status = col.listen(k.applied, M.Applied), col.listen(M.status_key(robot, "driver"), M.Status)
        lock = col.lock
        host = kids.spawn(["driver", "--engage", "--link", "udp", "--config", str(cfg), "--robot", robot, "--mode",
                           "client", "--connect", tcp(port), "--duration", "80"])
        pub = session.declare_publisher(k.cmd)
        epoch, seq = M.new_epoch(), 0

        def drive(seconds: float, done=lambda: True, longest: float = 20.0) -> None:
            """A station's commands for ``seconds``, and on until ``done()`` (a stalled host takes longer), at most
            ``longest`` s."""
            nonlocal seq
            t0, pace = time.monotonic(), Pace(0.05)
            while time.monotonic() - t0 < seconds or (time.monotonic() - t0 < longest and not col.holds(done)):
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=0.2, omega=0.0, method="scm",
                                           epoch=epoch)))
                seq += 1
                pace.wait()  # pacing: the station's 20 Hz

        assert col.wait(lambda: any(s.ok for s in status), 30)
        drive(1.0, lambda: any(a.reason == "cmd" for a in applied))
        with lock:
            assert any(a.reason == "cmd" for a in applied)
        pause = 2.5  # long enough that a host the machine stalls still shows its stop before the telemetry is back
        dev.pause_telemetry(pause)
        t_pause = time.monotonic()

        def stopped() -> bool:
            return (any(a.stamp > t_pause + 0.8 for a in applied)
                    and any(s.stamp > t_pause + 0.5 and ("no state from the robot" in s.text
                                                         or "no telemetry" in s.text) for s in status))

        drive(1.2, stopped, longest=pause - 0.3)
        assert time.monotonic() < t_pause + pause, "the host showed nothing of the pause before it ended"
        with lock:
            late = [a for a in applied if a.stamp > t_pause + 0.8]
            texts = [s.text for s in status if s.stamp > t_pause + 0.5]
        assert late and all(a.v == 0.0 and a.reason in ("no_telemetry", "fault") for a in late), \
            {a.reason for a in late}
        assert any("no state from the robot" in t or "no telemetry" in t for t in texts), texts
        # telemetry is back: driving again (on until the robot took the commands: it moves)
        drive(1.0, lambda: applied[-1].reason == "cmd" and vehicle.state.v > 0.0)
        with lock:
            assert applied[-1].reason == "cmd"
        moving_before = vehicle.state.v
        os.killpg(host.pid, signal.SIGKILL)
        t_kill = time.monotonic()
        drive(0.3)  # the station keeps sending; nobody passes it on
        until(lambda: vehicle.state.v == 0.0 and not vehicle.moving, 10.0)  # the robot's watchdog
        assert moving_before > 0.0 and vehicle.state.v == 0.0 and not vehicle.moving
        assert time.monotonic() - t_kill < 2.0


def test_a_failed_final_save_is_an_error_and_a_non_zero_exit(tmp_path) -> None:
    """Finding: with a full disk at SIGTERM the last save failed, the log said "pair store saved", exit 0."""
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])):
        res = subprocess.run([sys.executable, "-m", "bridge", "station", "--robot", "fs1", "--mode", "client",
                              "--connect", tcp(port), "--store", "/proc/scmbridge-test/pairs.bin", "--duration", "2"],
                             capture_output=True, text=True, timeout=120)
    assert res.returncode == 1, res.stderr[-2000:]
    assert "pair store NOT saved" in res.stderr and "pair store saved to" not in res.stderr
