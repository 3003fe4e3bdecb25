"""One backoff for everything that retries something that is not there yet (a router, a vehicle, a CAN bus, a
connection): the wait starts at ``initial`` and doubles at each failure up to ``maximum``; a success resets it."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Backoff:
    """``delay``: the wait before the next attempt; ``grow()`` after a failure, ``reset()`` after a success."""

    initial: float
    maximum: float
    factor: float = 2.0
    delay: float = field(init=False)

    def __post_init__(self) -> None:
        if not (0 < self.initial <= self.maximum and self.factor >= 1):
            raise ValueError(f"backoff from {self.initial} to {self.maximum} by {self.factor}: "
                             "need 0 < initial <= maximum and factor >= 1")
        self.delay = self.initial

    def grow(self) -> float:
        """Lengthen the wait (a failed attempt); returns the new one."""
        self.delay = min(self.delay * self.factor, self.maximum)
        return self.delay

    def reset(self) -> None:
        """Back to the first wait (it worked)."""
        self.delay = self.initial


__all__ = ["Backoff"]
