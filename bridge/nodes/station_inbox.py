"""What arrives for one robot's station (:class:`bridge.nodes.station.Station`), from Zenoh's callback threads: each
callback only decodes, counts, checks a mission request's address (:mod:`bridge.core.acts`) and puts what came into
a typed :class:`Inbox` under :attr:`Receiver.lock`, which the station's loop holds only to swap the inbox out; a
query, an external teacher's command and a driver host status a query waits for wake the loop
(docs/ARCHITECTURE.md, "bridge/nodes")."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from bridge.core import wire as M
from bridge.core.acts import ActGuard
from bridge.core.clock import Clock
from bridge.core.config import mission_from_spec
from bridge.nodes.node import Inputs
from bridge.nodes.station_core import TickInputs
from transfer.mission import Mission

log = logging.getLogger("scmbridge.station")


@dataclass
class Asked:
    """A query waiting for the loop: ``kind`` "control" or "pairs"; ``request`` the decoded mission request, or
    why it is malformed (str); ``at`` its receipt time."""

    kind: str
    query: zenoh.Query
    request: M.MissionRequest | str | None
    at: float


class Inbox:
    """What arrived since the last tick (taken, and so emptied, by :meth:`take`): from the callbacks, and the
    telemetry queues read at the tick. ``foreign``: commands of another sender on this robot's key; ``queries``:
    the ``control`` and ``pairs`` queries waiting for the loop (kind, the query, the decoded request or why it is
    malformed, receipt time)."""

    def __init__(self) -> None:
        self.telemetry: list[tuple[M.LearnerState | M.Applied, float]] = []
        self.driver: tuple[M.Status, float] | None = None
        self.mission: tuple[M.MissionSpec, Mission] | None = None
        self.teacher: tuple[M.TeacherCommand, float] | None = None
        self.foreign: list[tuple[M.Command, float]] = []
        self.queries: list[Asked] = []

    def take(self, periodic: bool, input_counts: dict[str, int], missed: int) -> TickInputs:
        out = TickInputs(tuple(self.telemetry), self.driver, self.mission, self.teacher, periodic, input_counts,
                         missed)
        self.telemetry, self.driver, self.mission, self.teacher = [], None, None, None
        return out


class Receiver:
    """The station's callbacks (``on_*``): what arrives goes into :attr:`inbox` under :attr:`lock` (held briefly,
    never for a tick; it also guards the core while no loop runs). ``epoch``: this run's (mission requests are
    addressed to it, :attr:`acts`; a command on the robot's key with another is another sender's); ``inputs``: the
    station's counted subscriptions (a malformed or refused request is counted there); ``wake``: wakes the loop;
    ``answer``: answers queries at once when no loop runs (:attr:`looping` False: nothing else calls the core)."""

    def __init__(self, epoch: int, inputs: Inputs, clock: Clock, wake: Callable[[], None],
                 answer: Callable[[list[Asked], float], None], off: Callable[..., None] | None = None) -> None:
        self.inputs, self.clock, self.wake, self.answer = inputs, clock, wake, answer
        #: runs ``off(fn, *args)`` what a callback must not do on its own thread (a query answered while no loop
        #: runs): the station's callbacks run on Zenoh's thread and give it an :class:`~bridge.nodes.node.OffThread`;
        #: None: at once, in the callback
        self.off = off if off is not None else _now
        self.lock = threading.Lock()
        self.inbox = Inbox()
        self.looping = False  # the loop runs: only its thread calls the core
        #: mission requests are addressed to this run, taken fresh and once (bridge.core.acts); under the lock
        self.acts = ActGuard(epoch)

    def take(self) -> Inbox:
        """What arrived since the last take (the inbox is swapped for an empty one)."""
        with self.lock:
            inbox, self.inbox = self.inbox, Inbox()
        return inbox

    def take_queries(self) -> tuple[list[Asked], bool, tuple[M.Status, float] | None]:
        """Between two ticks: the queries waiting, whether an external teacher's command waits, and the driver host's
        latest status when a query waits (the request is judged on the robot as it is now)."""
        with self.lock:
            queries, self.inbox.queries = self.inbox.queries, []
            return queries, self.inbox.teacher is not None, self.inbox.driver if queries else None

    def requeue(self, queries: list[Asked]) -> None:
        """Put queries back at the head of the inbox (they wait for a driver host status)."""
        with self.lock:
            self.inbox.queries[:0] = queries

    def begin(self) -> None:
        """From here on only the loop's thread calls the core (queries wait in the inbox for it)."""
        with self.lock:
            self.looping = True

    def end(self, now: float) -> None:
        """The loop has ended: queries left waiting are answered now; later ones in their callbacks."""
        with self.lock:
            self.looping = False
            left, self.inbox.queries = self.inbox.queries, []
            self.answer(left, now)

    def on_own_cmd(self, cmd: M.Command, now: float) -> None:
        """Commands on this robot's key from other sessions (this one's own are not delivered): one this station did
        not send is another station's (or a forger's)."""
        if cmd.epoch != self.acts.epoch:  # fixed at start: read without the lock
            with self.lock:
                self.inbox.foreign.append((cmd, now))

    def on_driver_status(self, st: M.Status, now: float) -> None:
        with self.lock:
            self.inbox.driver = (st, now)
            waiting = bool(self.inbox.queries)
        if waiting:  # a request may be waiting for it (SETTLE_S)
            self.wake()

    def on_control_query(self, query: zenoh.Query) -> None:
        """A person's request (``scmbridge mission ...``): decoded here, done or refused by the loop and answered
        at once (the station's ``_answer``). Every action but ``status`` must be fresh and new
        (:mod:`bridge.core.acts`): a recorded request replayed, or one without a time and nonce, is answered with the
        refusal and does nothing."""
        now = self.clock()
        try:
            payload = query.payload
            req: M.MissionRequest | str = M.decode(payload.to_bytes() if payload is not None else b"",
                                                   M.MissionRequest)
        except M.MessageError as exc:
            self.inputs.count("malformed_control")
            req = f"malformed request: {exc}"
        if isinstance(req, M.MissionRequest) and req.action != "status":
            with self.lock:
                why = self.acts.check(req.target, req.echo, req.nonce, req.source, now)
            if why is not None:
                self.inputs.count(f"control_refused_{why.kind}")
                say = log.debug if why.kind == "unaddressed" else log.warning
                say("mission %s by %r %s", req.action, req.source, why.text)
                req = why.text
        self._ask(Asked("control", query, req, now))

    def on_mission(self, spec: M.MissionSpec, now: float) -> None:
        try:
            mission = mission_from_spec(spec)
        except ValueError as exc:
            self.inputs.count("malformed_mission")
            log.warning("mission %r refused: %s", spec.name, exc)
            return
        with self.lock:
            self.inbox.mission = (spec, mission)

    def on_teacher(self, t: M.TeacherCommand, now: float) -> None:
        with self.lock:
            self.inbox.teacher = (t, now)
        self.wake()

    def on_pairs_query(self, query: zenoh.Query) -> None:
        self._ask(Asked("pairs", query, None, self.clock()))

    def _ask(self, asked: Asked) -> None:
        """Hand a query to the loop and wake it; when no loop runs, answer it by :attr:`off` (nothing else calls
        the core)."""
        with self.lock:
            queued = self.looping
            if queued:
                self.inbox.queries.append(asked)
        if queued:
            self.wake()
        else:
            self.off(self._answer_unless_looping, asked)

    def _answer_unless_looping(self, asked: Asked) -> None:
        """Answer ``asked`` now if no loop runs yet (or any more); else hand it to the loop."""
        with self.lock:
            if not self.looping:
                self.answer([asked], asked.at)
                return
            self.inbox.queries.append(asked)
        self.wake()


def _now(fn: Callable[..., None], *args: object) -> None:
    fn(*args)


__all__ = ["Asked", "Inbox", "Receiver"]
