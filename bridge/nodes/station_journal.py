"""What a station's core was given, published so that a recorded run can be replayed through a fresh core
(``scm/<robot>/journal``, :class:`bridge.core.wire.StationJournal`; ``scmbridge replay --through-station``,
docs/OPERATING.md "Why did it do that at t = 35 s").

The core is deterministic given what it is handed: its configuration, the pair store and mission state it starts
from, and, in order, each tick's inputs and time, the driver host's statuses noted between two ticks and the persons'
requests it acted on (the MPC's compiled code gives the same results as its interpreted functions, and the journal
says at which tick it came in). The inputs a tick takes are those the Zenoh adapter drained at that moment, with
its own receipt times: a recorder's copy of the poses and echoes, received at other moments, would not do. So the
station publishes each event as its core sees it, numbered from 0 at its start, only while someone subscribes (a
recorder; Zenoh's matching status): a station nobody records only counts (and keeps its first events, below). A
recorder started before the station is heard only a moment after the station declared its journal (Zenoh tells the
match on its own thread): the first :data:`BACKLOG_EVENTS` events are kept until then and sent first, so such a
recording starts at event 0; a station still unheard after them keeps nothing more.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from bridge.core import wire as M
from bridge.core.config import StationConfig
from bridge.nodes.mission_control import MissionControl, Saved
from bridge.nodes.node import on_zenoh
from bridge.nodes.station_core import StationCore, TickInputs

#: the digest of no file: the station started from an empty pair store
NO_STORE = "none"
#: the events kept from the start until someone subscribes (a recorder heard a moment late), 3 s at 10 Hz
BACKLOG_EVENTS = 30


def config_digest(cfg: StationConfig) -> str:
    """A short digest of a station configuration (every field, defaults included)."""
    return hashlib.sha256(msgspec.json.encode(cfg)).hexdigest()[:16]


def store_digest(path: Path) -> str:
    """A short digest of the pair store file a station starts from (:data:`NO_STORE` when there is none)."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except FileNotFoundError:
        return NO_STORE


def control_bytes(c: MissionControl) -> bytes:
    """The mission state a core starts from, as the journal's first event carries it (read, not saved)."""
    return msgspec.msgpack.encode(Saved(phase=c.phase, reason=c.reason, spec=c.spec,
                                        progress=min(1.0, max(0.0, float(c.progress))), guard=c.guard))


def control_from(robot: str, data: bytes) -> MissionControl:
    """The mission state :func:`control_bytes` carried, as the core had it (a running mission stays running)."""
    saved = msgspec.msgpack.decode(data, type=Saved)
    c = MissionControl(robot, saved.spec, saved.phase, saved.reason)
    c.progress, c.guard = saved.progress, saved.guard
    return c


def tick_inputs(j: M.StationJournal) -> TickInputs:
    """A ``tick`` event's inputs as the core was handed them."""
    from bridge.core.config import mission_from_spec

    telemetry = tuple((M.decode(s.data, M.Applied if s.kind == "applied" else M.LearnerState), s.at)
                      for s in j.telemetry)
    mission = None
    if j.mission:
        spec = M.decode(j.mission, M.MissionSpec)
        mission = (spec, mission_from_spec(spec))
    return TickInputs(telemetry=telemetry,
                      driver=(M.decode(j.driver, M.Status), j.driver_at) if j.driver else None,
                      mission=mission,
                      teacher=(M.decode(j.teacher, M.TeacherCommand), j.teacher_at) if j.teacher else None,
                      periodic=j.periodic, input_counts=dict(j.input_counts), missed_deadlines=j.missed)


class Journal:
    """One station's journal: :meth:`tick`, :meth:`driver` and :meth:`request` number each event the core is
    given and publish it while heard (module docstring). Called from the station's loop thread only (and before
    the loop, from a query's callback, as the core itself is)."""

    def __init__(self, core: StationCore, cfg: StationConfig, store_path: Path, always: bool = False) -> None:
        self.core, self.always = core, always
        self.seq = 0
        self.pub: Any = None
        self.heard = False
        self.head: dict[str, Any] = {"robot": core.robot, "rate_hz": 1.0 / core.time.period,
                                     "wall_offset": core.time.wall_offset, "config": config_digest(cfg),
                                     "store": store_digest(store_path)}
        self.control = control_bytes(core.control)
        self.backlog: list[bytes] | None = []  # the first events, encoded, until heard (None: no longer kept)

    def declare(self, session: zenoh.Session, keep) -> None:
        """Its publisher on ``session`` (``keep``: the station's declarations, undeclared with them), following
        whether anyone subscribes."""
        self.pub = keep(session.declare_publisher(M.key(self.core.robot, "journal")))
        if not self.always:
            keep(self.pub.declare_matching_listener(on_zenoh(self._on_matching)))  # sets a flag
            self.heard = bool(self.pub.matching_status.matching)

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:  # Zenoh's thread
        self.heard = bool(status.matching)

    @property
    def wanted(self) -> bool:
        """Whether the next event is to be built: someone hears it, or it is one of the first ones kept."""
        return self.always or self.heard or self.backlog is not None

    def _put(self, now: float, event: str, **fields: Any) -> None:
        seq, self.seq = self.seq, self.seq + 1
        if not self.wanted:
            return
        if seq == 0:
            fields["control"] = self.control
        data = M.encode(M.StationJournal(stamp=now, seq=seq, epoch=self.core.outbox.epoch, event=event, **self.head,
                                         **fields))
        if self.pub is not None and (self.always or self.heard):
            for kept in self.backlog or ():
                self.pub.put(kept)
            self.backlog = None
            self.pub.put(data)
        elif self.backlog is not None:
            self.backlog.append(data)
            if len(self.backlog) >= BACKLOG_EVENTS:
                self.backlog = None  # nobody came: a station nobody records keeps nothing

    def tick(self, inputs: TickInputs, now: float, compiled: bool) -> None:
        """A tick at ``now`` given ``inputs``; ``compiled``: the MPC runs its compiled code."""
        if not self.wanted:
            self.seq += 1
            return
        enc = M.encode
        telemetry = [M.JournalSample(kind="applied" if isinstance(m, M.Applied) else "state", at=at, data=enc(m))
                     for m, at in inputs.telemetry]
        fields: dict[str, Any] = {"periodic": inputs.periodic, "telemetry": telemetry, "compiled": compiled,
                                  "input_counts": dict(inputs.input_counts), "missed": inputs.missed_deadlines}
        if inputs.driver is not None:
            fields["driver"], fields["driver_at"] = enc(inputs.driver[0]), inputs.driver[1]
        if inputs.mission is not None:
            fields["mission"] = enc(inputs.mission[0])
        if inputs.teacher is not None:
            fields["teacher"], fields["teacher_at"] = enc(inputs.teacher[0]), inputs.teacher[1]
        self._put(now, "tick", **fields)

    def driver(self, st: M.Status, at: float, now: float) -> None:
        """The driver host's status (received at ``at``) noted between two ticks, at ``now``."""
        self._put(now, "driver", driver=M.encode(st), driver_at=at)

    def request(self, req: M.MissionRequest, now: float) -> None:
        """A person's mission request handed to the core at ``now``."""
        self._put(now, "request", request=M.encode(req))


__all__ = ["BACKLOG_EVENTS", "NO_STORE", "Journal", "config_digest", "control_bytes", "control_from", "store_digest",
           "tick_inputs"]
