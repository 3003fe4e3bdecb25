"""The station's journal (bridge/nodes/station_journal.py): each event its core is given, numbered from its start,
published while someone subscribes (Zenoh's matching status, on a real in-process session), and read back as the
very inputs the core had; the mission state it started with carried by the first event."""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import zenoh

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission_spec, mission_from_spec
from bridge.nodes.mission_control import Fitness, MissionControl
from bridge.nodes.station_core import StationCore, TickInputs
from bridge.nodes.station_journal import (
    BACKLOG_EVENTS,
    NO_STORE,
    Journal,
    config_digest,
    control_from,
    store_digest,
    tick_inputs,
)
from tests.fakeclock import FakeClock


def _until(fn, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while not fn():
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


def test_events_are_numbered_from_the_start_and_published_while_heard(tmp_path: Path, clock: FakeClock) -> None:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    spec = load_mission_spec(None)
    control = MissionControl("jr", spec)
    control.request(M.MissionRequest(stamp=0.0, action="start", source="test"), Fitness(""), 0.0)
    control.progress = 0.25
    core = StationCore(StationConfig(), "jr", 10.0, tmp_path / "p.bin", control.mission, control, clock=clock)
    journal = Journal(core, StationConfig(), tmp_path / "p.bin")
    state = M.LearnerState(stamp=1.0, seq=3, x=0.5, y=-0.25, theta=0.125)
    applied = M.Applied(stamp=1.01, seq=2, v=0.1, omega=-0.2, reason="cmd", cmd_seq=2)
    driver = M.Status(stamp=0.9, seq=7, node="driver", ok=True, reason="ok")
    teacher = M.TeacherCommand(stamp=1.02, seq=4, v=0.3, omega=0.1, sender="lab")
    inputs = TickInputs(telemetry=((applied, 1.011), (state, 1.012)), driver=(driver, 1.013),
                        mission=(spec, mission_from_spec(spec)), teacher=(teacher, 1.014), periodic=False,
                        input_counts={"malformed_state": 2}, missed_deadlines=1)
    heard: list[M.StationJournal] = []
    lock = threading.Lock()
    with zenoh.open(conf) as s:
        journal.declare(s, lambda h: h)
        assert not journal.heard
        journal.tick(TickInputs(), 1.0, False)  # nobody listens yet: numbered and kept, not sent

        def on(sample: zenoh.Sample) -> None:
            with lock:
                heard.append(M.decode(sample.payload.to_bytes(), M.StationJournal))

        s.declare_subscriber(M.key("jr", "journal"), on)
        assert _until(lambda: journal.heard), "the journal never heard its subscriber"
        journal.tick(inputs, 1.1, True)
        journal.driver(driver, 1.013, 1.15)
        journal.request(M.MissionRequest(stamp=0.0, action="pause", source="test"), 1.16)
        assert _until(lambda: len(heard) == 4)
    first, tick, noted, asked = heard  # the one kept from before the subscriber came, first
    assert [j.seq for j in heard] == [0, 1, 2, 3] and [j.event for j in heard] == ["tick", "tick", "driver", "request"]
    assert first.stamp == 1.0 and first.control == journal.control and not first.telemetry
    assert tick.stamp == 1.1 and tick.compiled and tick.epoch == core.outbox.epoch and tick.robot == "jr"
    back = tick_inputs(tick)  # the very inputs, with their receipt times
    assert dataclasses.replace(back, mission=None) == dataclasses.replace(inputs, mission=None)
    assert back.mission is not None and back.mission[0] == spec
    assert (back.mission[1].path.points == inputs.mission[1].path.points).all()
    assert M.decode(noted.driver, M.Status) == driver and noted.driver_at == 1.013
    assert M.decode(asked.request, M.MissionRequest).action == "pause"
    assert tick.config == config_digest(StationConfig()) and tick.store == NO_STORE == store_digest(tmp_path / "none")
    assert tick.wall_offset == core.time.wall_offset == clock.wall_offset
    assert not tick.control  # only the first event carries the mission state


def test_the_first_event_carries_the_mission_state_the_core_started_with(tmp_path: Path) -> None:
    spec = load_mission_spec(None)
    control = MissionControl("jr", spec)
    control.request(M.MissionRequest(stamp=0.0, action="start", source="test"), Fitness(""), 0.0)
    control.progress = 0.25
    core = StationCore(StationConfig(), "jr", 10.0, tmp_path / "p.bin", control.mission, control)
    back = control_from("jr", Journal(core, StationConfig(), tmp_path / "p.bin").control)
    assert (back.phase, back.reason, back.progress, back.spec) == ("running", control.reason, 0.25, spec)
    assert control.changed  # reading it saved nothing


def test_a_station_nobody_hears_keeps_only_its_first_events(tmp_path: Path, clock: FakeClock) -> None:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    core = StationCore(StationConfig(), "jn", 10.0, tmp_path / "p.bin", load_mission_spec_mission(), clock=clock)
    journal = Journal(core, StationConfig(), tmp_path / "p.bin")
    heard: list[int] = []
    with zenoh.open(conf) as s:
        journal.declare(s, lambda h: h)
        for k in range(BACKLOG_EVENTS + 5):
            journal.tick(TickInputs(), 1.0 + 0.1 * k, False)
        assert journal.backlog is None and journal.seq == BACKLOG_EVENTS + 5  # numbered, no longer kept
        s.declare_subscriber(M.key("jn", "journal"),
                             lambda sample: heard.append(M.decode(sample.payload.to_bytes(), M.StationJournal).seq))
        assert _until(lambda: journal.heard)
        journal.tick(TickInputs(), 20.0, False)
        assert _until(lambda: len(heard) == 1)
    assert heard == [BACKLOG_EVENTS + 5]  # a replay of this recording is refused: its first events are not in it


def load_mission_spec_mission():
    return mission_from_spec(load_mission_spec(None))
