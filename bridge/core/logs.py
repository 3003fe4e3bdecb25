"""Logs a person can read: a reason said once while it lasts, with how often and how long it held when it changes
(docs/OPERATING.md, "Reading the logs").

A service decides each tick (10 or 50 a second) and its words often carry a figure that changes every tick ("no pose
for 0.6 s", "0.7 s", ...): logged as they change, two short outages made 48 lines. :class:`ReasonLog` logs a reason
when its typed key changes (never on its words alone), counts the ticks it repeats, and says on the next change how
long the last one held and how often it was decided; :meth:`ReasonLog.flush` says it at the end of a run. Pure: the
times are arguments, no thread.
"""

from __future__ import annotations

import logging
from collections.abc import Hashable


class ReasonLog:
    """One service's reason in its log (see the module docstring); ``logger`` and ``level`` are where it goes."""

    def __init__(self, logger: logging.Logger, level: int = logging.INFO) -> None:
        self.log, self.level = logger, level
        self.key: Hashable | None = None
        self.text = ""
        self.since = 0.0
        self.repeats = 0  # decisions of the same key after the one logged

    def say(self, key: Hashable, text: str, now: float) -> bool:
        """The reason decided at ``now``: logged when ``key`` differs from the last one's (with how the last one held),
        counted otherwise. Returns whether it was logged."""
        if key == self.key:
            self.repeats += 1
            self.text = text
            return False
        self.log.log(self.level, "%s%s", text, self._held(now))
        self.key, self.text, self.since, self.repeats = key, text, now, 0
        return True

    def _held(self, now: float) -> str:
        """`` (after: <the last words>, held 4.8 s, decided 48 times)`` for a reason that repeated, else ""."""
        if self.key is None or not self.repeats:
            return ""
        return f" (after: {self.text}; held {now - self.since:.1f} s, decided {self.repeats + 1} times)"

    def flush(self, now: float) -> None:
        """At the end of a run: how the last reason held, if it repeated since it was logged."""
        if self.key is not None and self.repeats:
            self.log.log(self.level, "last: %s; held %.1f s, decided %d times", self.text, now - self.since,
                         self.repeats + 1)
            self.repeats = 0


__all__ = ["ReasonLog"]
