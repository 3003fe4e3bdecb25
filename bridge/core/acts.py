"""A person's acts, fresh and once: the replay guard of the requests that let a robot drive (the guard is pure:
times are arguments; :func:`stamped` reads the wall clock for a tool; docs/ARCHITECTURE.md section 6, "A person is in
charge").

Engaging a driver host (:class:`bridge.core.wire.EngageRequest`), the station's mission requests
(:class:`bridge.core.wire.MissionRequest`: start, pause, resume, abort, send) and releasing an estop
(:class:`bridge.core.wire.Estop` with ``engaged=False``) carry the wall-clock time the person's tool made them
(``time.time()``: the tool and the node may run on different machines, so no monotonic clock is shared) and a random
nonce. The receiver takes a request only if its time is within :data:`WINDOW_S` of its own clock (either way: clocks
of two machines differ a little) and its nonce was not seen within that window. So a payload recorded off the
network and replayed later does nothing: found replayed 60 s later, a recorded engage drove the robot 0.09 s after.
A request without them (an old tool, or a recorded old-format payload) is refused too, with the reason: what
decodes with the fields' safe defaults is not thereby accepted.

A stop is never checked: an estop that latches, a hand-back (disengage) and a status query are always honoured.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import TypeVar

import msgspec

from bridge.core import wire as M

#: a request stamped further than this from the receiver's wall clock (before or after) is refused, s
WINDOW_S = 10.0
#: nonces kept at most (each for the window); beyond, new requests are refused until old ones expire (a flood of
#: fresh requests is refused rather than forgetting the nonces that keep replays out)
MAX_NONCES = 4096


@dataclass(frozen=True)
class Refusal:
    """Why a request was refused: ``kind`` (unstamped, stale, future, replayed, flooded: what programs count) and
    ``text`` (for the person, starting with "refused: ")."""

    kind: str
    text: str


class ActGuard:
    """Takes a request stamped ``wall_time`` with ``nonce`` once, while fresh: :meth:`check` returns None (taken:
    its nonce is kept until it could no longer be fresh) or the :class:`Refusal`."""

    def __init__(self, window_s: float = WINDOW_S, max_nonces: int = MAX_NONCES) -> None:
        self.window_s = float(window_s)
        self.max_nonces = int(max_nonces)
        self.seen: OrderedDict[str, float] = OrderedDict()  # nonce -> until when it is kept (wall clock)
        self.refused = {"unstamped": 0, "stale": 0, "future": 0, "replayed": 0, "flooded": 0}

    def check(self, wall_time: float, nonce: str, now_wall: float) -> Refusal | None:
        """None when the request is fresh and new (its nonce is then remembered), else the refusal."""
        self._forget(now_wall)
        if wall_time <= 0.0 or not nonce:
            return self._refuse("unstamped", "refused: the request carries no time and nonce (an old tool, or a "
                                "recorded request replayed); use this version's scmbridge")
        age = now_wall - wall_time
        if age > self.window_s:
            return self._refuse("stale", f"refused: the request was made {age:.1f} s ago by this host's clock (more "
                                f"than {self.window_s:g} s): a recorded request replayed, or the two machines' "
                                "clocks differ (synchronise them: NTP)")
        if -age > self.window_s:
            return self._refuse("future", f"refused: the request is stamped {-age:.1f} s ahead of this host's clock "
                                f"(more than {self.window_s:g} s): the two machines' clocks differ (synchronise "
                                "them: NTP)")
        if nonce in self.seen:
            return self._refuse("replayed", "refused: this request was already received once (a replay): ask again")
        if len(self.seen) >= self.max_nonces:
            return self._refuse("flooded", f"refused: more than {self.max_nonces} requests within "
                                f"{self.window_s:g} s: try again shortly")
        # kept until it could no longer be fresh: a request stamped ahead stays fresh until its time + the window
        self.seen[nonce] = max(wall_time, now_wall) + self.window_s
        return None

    def _refuse(self, kind: str, text: str) -> Refusal:
        self.refused[kind] += 1
        return Refusal(kind, text)

    def _forget(self, now_wall: float) -> None:
        """Drop the nonces whose requests can no longer be fresh (their stamps are older than the window)."""
        for nonce in [n for n, until in self.seen.items() if until < now_wall]:
            del self.seen[nonce]


R = TypeVar("R", M.EngageRequest, M.MissionRequest, M.Estop)


def stamped(req: R) -> R:
    """``req`` stamped now (this machine's wall clock) with a new nonce: what a person's tool sends, once per try."""
    return msgspec.structs.replace(req, wall_time=time.time(), nonce=M.new_nonce())


__all__ = ["MAX_NONCES", "WINDOW_S", "ActGuard", "Refusal", "stamped"]
