"""A station core's journal replayed through a fresh core (bridge/tools/replay_station.py), in process: the same
journal gives the same commands bit for bit; a changed input, store or configuration gives the first tick whose
command differs, and why. The journal travels over a real Zenoh session (in process, no endpoint); the run's robot is
the paper's learner fed each command. The whole path (a recorded run of real processes, the command line) is
tests/integration/test_replay_station.py."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh

from bridge.core import wire as M
from bridge.core.config import StationConfig, from_table, load_mission_spec
from bridge.core.paths import save_atomic
from bridge.nodes.mission_control import Fitness, MissionControl
from bridge.nodes.station_core import StationCore, TickInputs
from bridge.nodes.station_journal import Journal
from bridge.tools.replay_station import Run, replay, report
from sim_learner.dynamics import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W, mpc_learner
from tests.fakeclock import FakeClock
from transfer.domain import Bounds
from transfer.store import PairStore

ROBOT = "j1"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Run:
    """40 ticks of a core driving the paper's learner at 10 Hz on a fake clock, its journal heard on Zenoh."""
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    heard: list[M.StationJournal] = []
    lock = threading.Lock()
    clock = FakeClock()
    control = MissionControl(ROBOT, load_mission_spec(None))
    control.request(M.MissionRequest(stamp=0.0, action="start", source="test"), Fitness("not checked yet"), 0.0)
    core = StationCore(StationConfig(), ROBOT, 10.0, tmp_path_factory.mktemp("run") / "p.bin", control.mission,
                       control, clock=clock)
    journal = Journal(core, StationConfig(), Path("/nonexistent"), always=True)
    run = Run(ROBOT)
    with zenoh.open(conf) as s:
        def on(sample: zenoh.Sample) -> None:
            with lock:
                heard.append(M.decode(sample.payload.to_bytes(), M.StationJournal))

        s.declare_subscriber(M.key(ROBOT, "journal"), on)
        journal.declare(s, lambda h: h)
        learner, x = mpc_learner(), np.array(control.mission.start, dtype=float)
        pending: list = []
        for k in range(40):
            now = clock.advance(0.1)
            pose = M.LearnerState(stamp=now - 0.01, seq=k, x=float(x[0]), y=float(x[1]), theta=float(x[2]))
            driver = M.Status(stamp=now, seq=k, node="driver", ok=True, text="driving", reason="ok")
            inputs = TickInputs(telemetry=((pose, now - 0.005), *pending), driver=(driver, now - 0.002))
            journal.tick(inputs, now, False)
            cmd = core.tick(inputs, now).command
            run.commands[(cmd.epoch, cmd.seq)] = cmd
            x = learner.step(x, np.array([cmd.v, cmd.omega]), 0.1)
            pending = [(M.Applied(stamp=now + 0.001, seq=cmd.seq, v=cmd.v, omega=cmd.omega, cmd_seq=cmd.seq,
                                  reason="stop" if cmd.method == "stop" else "cmd"), now + 0.003)]
        end = time.monotonic() + 10
        while len(heard) < 40 and time.monotonic() < end:
            time.sleep(0.01)
    run.journal = sorted(heard, key=lambda j: j.seq)
    assert [j.seq for j in run.journal] == list(range(40))
    assert sum(c.method != "stop" for c in run.commands.values()) >= 20, "the run never drove"
    return run


def test_the_same_journal_gives_the_same_commands_bit_for_bit(recorded: Run) -> None:
    out = replay(recorded, StationConfig(), None)
    assert (out.ticks, out.same, out.first, out.notes, out.missing) == (40, 40, None, [], 0)
    text, code = report(out, ROBOT)
    assert code == 0 and "40 commands identical to the recorded ones, bit for bit" in text


def test_a_changed_input_names_the_first_tick_whose_command_differs(recorded: Run) -> None:
    journal = list(recorded.journal)
    j = journal[25]
    moved = [msgspec.structs.replace(s, data=M.encode(msgspec.structs.replace(M.decode(s.data, M.LearnerState),
                                                                               x=M.decode(s.data, M.LearnerState).x
                                                                               + 0.05)))
             if s.kind == "state" else s for s in j.telemetry]
    journal[25] = msgspec.structs.replace(j, telemetry=moved)  # the pose of tick 25 five centimetres off
    out = replay(Run(ROBOT, journal, recorded.commands), StationConfig(), None)
    assert out.first is not None, "a moved pose went unnoticed"
    n = int(out.first.split()[1])  # the first tick whose command differs: not before the pose moved, and it says when
    assert 25 <= n <= 30 and out.first.startswith(f"tick {n} (t = {(n) * 0.1:.2f} s after the first tick"), out.first
    assert out.same >= n
    text, code = report(out, ROBOT)
    assert code == 1 and "an input reached the core that the journal does not hold" in text


def test_a_different_store_or_configuration_is_named(recorded: Run, tmp_path: Path) -> None:
    seeded = PairStore(Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=1)
    for u in ([0.1, 0.0], [0.2, 0.1], [0.25, -0.1], [0.15, -0.2], [0.05, 0.3]):
        seeded.add([0.8 * u[0], 0.7 * u[1]], u)
    save_atomic(tmp_path / "s.bin", seeded.to_bytes())
    out = replay(recorded, StationConfig(), tmp_path / "s.bin")
    assert out.first is not None and any("pair store differs" in n for n in out.notes)
    out = replay(recorded, from_table({"station": {"horizon": 12}}, StationConfig, "test"), None)
    assert out.first is not None and any("configuration differs" in n for n in out.notes)
    text, code = report(out, ROBOT)
    assert code == 1 and "Why: the configuration differs" in text


def test_a_journal_without_its_first_events_or_with_a_gap_is_said(recorded: Run) -> None:
    from bridge.core.errors import UsageError

    with pytest.raises(UsageError, match="starts at event 3"):
        replay(Run(ROBOT, recorded.journal[3:], recorded.commands), StationConfig(), None)
    out = replay(Run(ROBOT, recorded.journal[:10] + recorded.journal[11:], recorded.commands), StationConfig(), None)
    assert out.ticks == 10 and any("before event 11" in n for n in out.notes)


def test_of_two_runs_recorded_the_first_to_begin_is_replayed(recorded: Run) -> None:
    later = [msgspec.structs.replace(j, epoch=1, stamp=j.stamp + 100.0) for j in recorded.journal]  # a restart
    out = replay(Run(ROBOT, later + recorded.journal, recorded.commands), StationConfig(), None)
    assert (out.same, out.first) == (40, None)
