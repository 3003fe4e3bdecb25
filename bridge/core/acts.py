"""A person's acts, addressed to one process, fresh and once: the replay guard of the requests that let a robot
drive (the guard is pure: times are arguments; :func:`stamped` reads the wall clock for a tool; docs/ARCHITECTURE.md
section 6, "The person's acts are fresh and once").

Engaging a driver host (:class:`bridge.core.wire.EngageRequest`), the station's mission requests
(:class:`bridge.core.wire.MissionRequest`: start, pause, resume, abort, send) and releasing an estop
(:class:`bridge.core.wire.Estop` with ``engaged=False``) are *addressed*: they carry the ``target`` epoch of the
process they are for and an ``echo`` of that process's own monotonic clock, both read off one of its answers (its
:class:`bridge.core.wire.EstopState`, :class:`bridge.core.wire.EngageState`, :class:`bridge.core.wire.MissionState`:
``epoch`` and ``stamp``), and a random nonce. The receiver takes a request only if it names its own epoch (a new one
at each start: nothing recorded before a restart is valid after it, whatever anyone's clocks say), its echo is
within :data:`WINDOW_S` of its own clock (a request recorded and replayed later is stale) and its nonce was not
seen from that source within the window. As UDP commands name the robot's boot (bridge/core/auth.py), so these name
the process: no clock of two machines is compared, so a robot whose wall clock is an hour off takes every act, and
stepping a clock forward and back revives none. The tool's ``wall_time`` is kept for the logs only.

A request that names no process (an older tool, a recorded old-format payload, or a new tool's first try) is
refused with kind ``unaddressed``; the refusal carries the receiver's epoch and clock, so the tool addresses its next
try (:func:`address_of`). Nonces are budgeted per source (:data:`PER_SOURCE` each, :data:`MAX_SOURCES` sources,
the persons of the configuration always admitted): a flood by one source refuses that source's acts and no one
else's. Sources are claimed names: under ``deploy lab`` only the operator's certificate may act at all.

A stop is never checked: an estop that latches, a hand-back (disengage) and a status query are always honoured.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import TypeVar

import msgspec

from bridge.core import wire as M

#: an act echoing its receiver's clock further back than this is refused as stale, s
WINDOW_S = 10.0
#: nonces kept per source at most (each for the window); beyond, that source's new acts are refused until its old
#: ones expire (a flood is refused rather than forgetting the nonces that keep replays out)
PER_SOURCE = 256
#: sources with nonces kept at once, besides the persons named in the configuration (always admitted)
MAX_SOURCES = 32
#: refusal kinds (what programs count)
KINDS = ("unaddressed", "other_process", "unstamped", "stale", "future", "replayed", "flooded")


@dataclass(frozen=True)
class Refusal:
    """Why a request was refused: ``kind`` (one of :data:`KINDS`) and ``text`` (for the person, starting with
    "refused: ")."""

    kind: str
    text: str


@dataclass(frozen=True)
class Address:
    """Which process an act is for: its ``epoch`` and a reading of its monotonic ``clock`` (from one answer)."""

    epoch: int
    clock: float


class ActGuard:
    """Takes a request addressed to ``epoch`` once, while fresh on the receiver's own clock: :meth:`check` returns
    None (taken: its nonce is kept until its echo is older than the window) or the :class:`Refusal`. ``persons``:
    the sources the configuration names (they always get a nonce budget of their own)."""

    def __init__(self, epoch: int, window_s: float = WINDOW_S, per_source: int = PER_SOURCE,
                 max_sources: int = MAX_SOURCES, persons: tuple[str, ...] = ("operator",)) -> None:
        self.epoch = int(epoch)
        self.window_s = float(window_s)
        self.per_source, self.max_sources = int(per_source), int(max_sources)
        self.persons = frozenset(persons)
        self.seen: dict[str, OrderedDict[str, float]] = {}  # source -> nonce -> until when it is kept (our clock)
        self.refused = dict.fromkeys(KINDS, 0)

    def address(self, now: float) -> Address:
        """What this receiver's answers carry (``epoch`` and ``stamp``), so a tool can address its act."""
        return Address(self.epoch, now)

    def check(self, target: int, echo: float, nonce: str, source: str, now: float) -> Refusal | None:
        """None when the request names this process, echoes a clock reading within the window of ``now`` (this
        receiver's monotonic clock) and carries a nonce new from ``source`` (it is then remembered), else why not."""
        self._forget(now)
        if not target:
            return self._refuse("unaddressed", "refused: the request names no process (an older tool, or a recorded "
                                "request replayed); use this version's scmbridge")
        if target != self.epoch:
            return self._refuse("other_process", f"refused: the request is for another start of this node (epoch "
                                f"{target:x}, this one is {self.epoch:x}): a request recorded before a restart, "
                                "replayed; ask again")
        if not nonce or echo <= 0.0:
            return self._refuse("unstamped", "refused: the request carries no nonce or no echo of this node's clock")
        age = now - echo
        if age > self.window_s:
            return self._refuse("stale", f"refused: the request answers this node's clock of {age:.1f} s ago (more "
                                f"than {self.window_s:g} s): a recorded request replayed; ask again")
        if age < 0.0:
            return self._refuse("future", "refused: the request echoes a reading of this node's clock not made yet "
                                "(forged)")
        mine = self.seen.get(source)
        if mine is not None and nonce in mine:
            return self._refuse("replayed", "refused: this request was already received once (a replay): ask again")
        if mine is None:
            others = sum(1 for s in self.seen if s not in self.persons)
            if source not in self.persons and others >= self.max_sources:
                return self._refuse("flooded", f"refused: acts of more than {self.max_sources} sources within "
                                    f"{self.window_s:g} s: try again shortly")
            mine = self.seen[source] = OrderedDict()
        if len(mine) >= self.per_source:
            return self._refuse("flooded", f"refused: more than {self.per_source} requests of {source!r} within "
                                f"{self.window_s:g} s: try again shortly")
        mine[nonce] = echo + self.window_s  # after that, its echo is stale: the nonce need not be kept
        return None

    def _refuse(self, kind: str, text: str) -> Refusal:
        self.refused[kind] += 1
        return Refusal(kind, text)

    def _forget(self, now: float) -> None:
        """Drop the nonces whose requests can no longer be fresh, and the sources left with none."""
        for source in list(self.seen):
            mine = self.seen[source]
            for nonce in [n for n, until in mine.items() if until < now]:
                del mine[nonce]
            if not mine:
                del self.seen[source]


R = TypeVar("R", M.EngageRequest, M.MissionRequest, M.Estop)


def stamped(req: R, to: Address | None = None) -> R:
    """``req`` with a new nonce, this machine's wall clock (for the logs) and, given ``to``, addressed to that
    process: what a person's tool sends, once per try (``to`` None: the first try, refused ``unaddressed`` with the
    address in the answer)."""
    target, echo = (to.epoch, to.clock) if to is not None else (0, 0.0)
    return msgspec.structs.replace(req, wall_time=time.time(), nonce=M.new_nonce(), target=target, echo=echo)


def address_of(answer: M.EstopState | M.EngageState | M.MissionState) -> Address | None:
    """The address an answer gives (None from a node older than the field)."""
    return Address(answer.epoch, answer.stamp) if answer.epoch else None


__all__ = ["KINDS", "MAX_SOURCES", "PER_SOURCE", "WINDOW_S", "ActGuard", "Address", "Refusal", "address_of",
           "stamped"]
