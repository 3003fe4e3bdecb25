"""``scmbridge replay --through-station RUN.mcap``: a recorded run's station fed again, in process, to a fresh core
on the recorded clock, its commands compared with the recorded ones bit for bit (docs/OPERATING.md, "Why did it do
that at t = 35 s").

The recording must hold the station's journal (``scm/<robot>/journal``, :mod:`bridge.nodes.station_journal`) from
its first event: a recorder started before the station. The core is built from the
configuration and the pair store given here (they should be the run's: the journal carries their digests, and a
difference is named), its mission state, epoch and wall-clock offset from the journal; then each event is handed to
it in order at its recorded time. Every command it makes is compared with the one the station published (same
seq): identical bytes, or the first tick that differs, with both commands and why (a different configuration or
store; else the code or its libraries differ, or the recording lost events).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.core import wire as M
from bridge.core.config import StationConfig
from bridge.core.errors import UsageError
from bridge.nodes.station_core import StationCore
from bridge.nodes.station_journal import NO_STORE, config_digest, control_from, store_digest, tick_inputs
from bridge.tools.mcap_format import iter_recording, parse_key


class RecordedClock:
    """The station's clock as the journal gives it: the time is the event's (:attr:`now`), the wall clock that
    plus the run's offset; durations (a tick's CPU time) are this process's own."""

    def __init__(self, wall_offset: float) -> None:
        self.now = 0.0
        self.wall_offset = wall_offset

    def __call__(self) -> float:
        return self.now

    def wall(self) -> float:
        return self.now + self.wall_offset

    @staticmethod
    def perf() -> float:
        return time.perf_counter()

    def wait(self, event: Any, timeout: float | None) -> bool:
        raise RuntimeError("a replayed station never waits: its events come from the recording")


@dataclass
class Run:
    """One robot's journal and published commands in a recording."""

    robot: str
    journal: list[M.StationJournal] = field(default_factory=list)
    commands: dict[tuple[int, int], M.Command] = field(default_factory=dict)  # (epoch, seq) -> command


def read_runs(files: list[str]) -> dict[str, Run]:
    """Every robot's journal (in event order) and commands in the recording."""
    runs: dict[str, Run] = {}
    for entry in iter_recording(files):
        if not entry.is_wire:
            continue
        try:
            robot, topic = parse_key(entry.topic)
        except ValueError:
            continue
        if topic == "journal":
            runs.setdefault(robot, Run(robot)).journal.append(entry.message())
        elif topic == "cmd":
            cmd = entry.message()
            runs.setdefault(robot, Run(robot)).commands[(cmd.epoch, cmd.seq)] = cmd
    for run in runs.values():
        run.journal.sort(key=lambda j: (j.epoch, j.seq))
    return runs


@dataclass
class Outcome:
    """What a replay found: ``ticks`` replayed, ``same`` commands identical, the first difference (None: none),
    and the notes on why it may differ."""

    ticks: int = 0
    same: int = 0
    first: str | None = None
    notes: list[str] = field(default_factory=list)
    missing: int = 0  # commands the replay made that the recording does not hold


def _compiled(core: StationCore) -> bool:
    """The MPC's compiled code in use, as the run's station switched to it (built or loaded from the cache); False
    when it cannot be here (no compiler, ``SCMBRIDGE_NO_COMPILE``): the replay goes on interpreted."""
    from bridge.teacher.codegen import compile_functions

    teacher = getattr(core.source, "teacher", None)
    if teacher is None or teacher.compiled or not teacher.kernels():
        return True
    functions = compile_functions(teacher.kernels())
    if functions is None:
        return False
    teacher.use_compiled(functions)
    return True


def _fields(c: M.Command) -> str:
    return f"{c.method} v={c.v!r} omega={c.omega!r}" + (f" region={list(c.region)}" if c.region else "")


def replay(run: Run, cfg: StationConfig, store: Path | None, epoch: int | None = None) -> Outcome:
    """Feed ``run``'s journal (of ``epoch``, default its first station run) to a fresh core built from ``cfg``
    and ``store`` (None: an empty one); compare each command it makes with the recorded one."""
    firsts: dict[int, float] = {}
    for j in run.journal:  # the runs in the order they began (a restarted station's stamps come later)
        firsts[j.epoch] = min(j.stamp, firsts.get(j.epoch, j.stamp))
    epochs = sorted(firsts, key=firsts.__getitem__)
    if not epochs:
        raise UsageError(f"the recording holds no journal of {run.robot}: record with the recorder started before "
                         "the station")
    epoch = epochs[0] if epoch is None else epoch
    events = [j for j in run.journal if j.epoch == epoch]
    out = Outcome()
    if events[0].seq != 0:
        raise UsageError(f"the journal of {run.robot} starts at event {events[0].seq}: the station's first events "
                         "were not recorded (start the recorder before the station)")
    head = events[0]
    if (c := config_digest(cfg)) != head.config:
        out.notes.append(f"the configuration differs from the run's (digest {c}, the run's {head.config})")
    if (s := store_digest(store) if store is not None else NO_STORE) != head.store:
        out.notes.append(f"the pair store differs from the one the run started from (digest {s}, the run's "
                         f"{head.store})")
    gaps = [b.seq for a, b in zip(events, events[1:]) if b.seq != a.seq + 1]
    if gaps:
        out.notes.append(f"the recording lost journal events before event {gaps[0]}: replayed up to there")
        events = [j for j in events if j.seq < gaps[0]]
    clock = RecordedClock(head.wall_offset)
    with tempfile.TemporaryDirectory(prefix="scmbridge-replay-") as tmp:
        path = Path(tmp) / "pairs.bin"
        if store is not None:
            shutil.copyfile(store, path)  # the core saves its store as it learns: never over the given file
        control = control_from(run.robot, head.control)
        # as the station's core: a command's left-over work done before the next tick (here, at its start)
        core = StationCore(cfg, run.robot, head.rate_hz, path, control.mission, control, None, clock=clock,
                           defer=True)
        core.outbox.epoch, core.time.wall_offset, core.latest.teacher_heard = epoch, head.wall_offset, False
        t0 = next((j.stamp for j in events if j.event == "tick"), head.stamp)
        for j in events:
            clock.now = j.stamp
            if j.event == "driver":
                core.note_driver(M.decode(j.driver, M.Status), j.driver_at)
                continue
            if j.event == "request":
                core.request(M.decode(j.request, M.MissionRequest), j.stamp)
                continue
            if j.compiled and not _compiled(core) and not any("compiled" in n for n in out.notes):
                out.notes.append("the run's MPC ran its compiled code from this tick on, the replay its interpreted "
                                 f"functions (no compiled code here): tick {out.ticks}")
            got = core.tick(tick_inputs(j), j.stamp).command
            out.ticks += 1
            if got is None:
                continue
            want = run.commands.get((epoch, got.seq))
            if want is None:
                out.missing += 1
                continue
            if M.encode(want) == M.encode(got):
                out.same += 1
                continue
            if out.first is None:
                out.first = (f"tick {out.ticks - 1} (t = {j.stamp - t0:.2f} s after the first tick, command seq "
                             f"{got.seq}): the run published {_fields(want)}, the replay {_fields(got)}")
    return out


def report(out: Outcome, robot: str) -> tuple[str, int]:
    """The replay's verdict in words and its exit code (0: every command identical)."""
    why = "; ".join(out.notes)
    if out.first is None and out.same and not out.notes:
        text = (f"{robot}: replayed {out.ticks} ticks through a fresh station: {out.same} commands identical to the "
                "recorded ones, bit for bit")
        if out.missing:
            text += f" ({out.missing} the recording does not hold were not compared)"
        return text, 0
    if out.first is None:
        if not out.same:
            return f"{robot}: replayed {out.ticks} ticks: no command to compare" + (f" ({why})" if why else ""), 1
        return (f"{robot}: replayed {out.ticks} ticks through a fresh station: {out.same} commands identical to the "
                f"recorded ones, bit for bit, although {why}"), 0
    because = why or ("the configuration and the store are the run's: the station's code or its libraries differ "
                      "from the run's, or an input reached the core that the journal does not hold")
    return (f"{robot}: replayed {out.ticks} ticks; the first command that differs is at {out.first} "
            f"({out.same} of the commands identical in all). Why: {because}"), 1


__all__ = ["Outcome", "RecordedClock", "Run", "read_runs", "replay", "report"]
