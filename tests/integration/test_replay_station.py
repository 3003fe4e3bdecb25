"""``scmbridge replay --through-station`` (bridge/tools/replay_station.py): a short real run (a station driving the
emulated CAN learner through a driver host, over a Zenoh router on a free 127.0.0.1 port, recorded by ``scmbridge
record``) replayed through a fresh station core in process reproduces every command the station published, bit for
bit; a different store or configuration is named, with the first tick whose command differs. Recorded and replayed
on the same machine (no float is compared across machines)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.core.config import load_mission
from bridge.core.paths import save_atomic
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, said, stop_group
from bridge.tools.replay_station import read_runs
from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
from tests.collect import Collector
from tests.wait import until
from transfer.domain import Bounds
from transfer.store import PairStore

ROBOT = "replay1"


def _replay(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", "replay", "--through-station", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A few seconds of a station driving the emulated learner from the mission's start, recorded."""
    d = tmp_path_factory.mktemp("replay")
    out, port = d / "run.mcap", free_port()
    with pytest.MonkeyPatch.context() as env:  # (tests/conftest.py's per-test settings come after a module's fixture)
        env.setenv("SCMBRIDGE_STATE_DIR", str(d / "state"))
        env.setenv("SCMBRIDGE_RECORD_DIR", str(d / "record"))
        env.setenv("SCMBRIDGE_NO_COMPILE", "1")
        _record(d, out, port)
    return out


def _record(d: Path, out: Path, port: int) -> None:
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    client = ["--robot", ROBOT, "--mode", "client", "--connect", tcp(port)]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as router, Children() as kids:
        rec = kids.spawn(["record", "--robot", ROBOT, "--out", str(out), "--mode", "client", "--connect", tcp(port)])
        assert until(lambda: "recording scm/" in said(rec) or rec.poll() is not None, 60, 0.1), said(rec)
        host = Collector(router).listen(M.status_key(ROBOT, "driver"), M.Status)
        driver = kids.spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", x0, *client, "--duration",
                             "90"])
        # the station's six seconds are for driving: it starts once the driver host says its vehicle is engaged and
        # fit (a loaded machine took longer than six seconds to start the driver host)
        assert until(lambda: any(st.engaged and st.ok for st in list(host)) or driver.poll() is not None, 60, 0.1), (
            said(driver))
        # the recorder came first: the station's journal from its first event (kept until the recorder is heard)
        station = kids.spawn(["station", *client, "--store", str(d / "pairs.bin"), "--start", "--duration", "6"])
        assert until(lambda: station.poll() is not None, 90, 0.2), said(station)
        assert station.returncode == 0, said(station)
        stop_group(rec)  # a clean stop: the file's summary written
        assert rec.returncode == 0, said(rec)


def test_a_recorded_run_replays_through_the_station_bit_for_bit(recorded: Path) -> None:
    run = read_runs([str(recorded)])[ROBOT]
    ticks = [j for j in run.journal if j.event == "tick"]
    assert len(ticks) >= 40 and run.journal[0].seq == 0
    driving = [c for c in run.commands.values() if c.method != "stop"]
    assert len(driving) >= 10, "the run never drove: nothing to reproduce"
    res = _replay(str(recorded))
    assert res.returncode == 0, res.stdout + res.stderr
    n = len(run.commands)
    assert f"{n} commands identical to the recorded ones, bit for bit" in res.stdout, res.stdout


def test_a_different_store_names_the_first_tick_that_differs_and_why(recorded: Path,
                                                                               tmp_path: Path) -> None:
    seeded = PairStore(Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    for u in ([0.1, 0.0], [0.2, 0.1], [0.25, -0.1], [0.15, -0.2], [0.05, 0.3]):
        seeded.add([0.8 * u[0], 0.7 * u[1]], u)  # a learner the run's was not
    store = tmp_path / "other.bin"
    save_atomic(store, seeded.to_bytes())
    res = _replay(str(recorded), "--store", str(store))
    assert res.returncode == 1, res.stdout + res.stderr
    assert "the first command that differs is at tick " in res.stderr, res.stderr
    assert "the run published" in res.stderr, res.stderr
    assert "the pair store differs from the one the run started from" in res.stderr, res.stderr

    # a different configuration, named the same way: tests/unit/bridge/tools/test_replay_station.py (in process)


def test_a_recording_without_the_stations_journal_says_how_to_make_one(tmp_path: Path) -> None:
    from bridge.tools.mcap_format import classify
    from bridge.tools.mcap_sink import McapSink

    out = tmp_path / "nojournal.mcap"
    sink = McapSink(out)  # the recorder's own writer: a run's commands, without the station's journal
    for seq in range(5):
        cmd = M.Command(stamp=1.0 + 0.1 * seq, seq=seq, v=0.0, omega=0.0, method="stop", valid_ms=300)
        for spec, data, _ in classify(M.key(ROBOT, "cmd"), M.encode(cmd)):
            sink.write(spec, data, log_time_ns=int((1.0 + 0.1 * seq) * 1e9))
    sink.close("done")
    res = _replay(str(out))
    assert res.returncode != 0 and "the recorder started before the station" in res.stderr, res.stdout + res.stderr
