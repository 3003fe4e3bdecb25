"""Saves written off a real-time loop: the loop hands over bytes it encoded, or a function that encodes a snapshot it
took (a :data:`Payload`: the encoding, the tag with it, then runs on the writer's thread too), a thread of their own
writes them (atomically: write, fsync, rename, fsync the directory; :func:`bridge.core.paths.save_atomic`), and the
loop collects each outcome at its next tick.

A slow or stalled disk then delays the file, never the loop's ticks: the station's commands go out on their
deadlines while a save waits for its fsync (docs/ARCHITECTURE.md, "Threads and clocks"). Per file the latest bytes
win: a save handed over while an older one of the same file still waits replaces it (the older snapshot is stale
anyway); one being written is finished first, so the file always ends with the latest.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

from bridge.core.paths import save_atomic

log = logging.getLogger("scmbridge.station")

#: a save: write ``data`` to ``path`` atomically, raising OSError on failure
Save = Callable[[Path, bytes], None]
#: what is handed over: the bytes, or a function that gives them (called once, on the writer's thread; it must read
#: only a snapshot the loop no longer changes)
Payload = bytes | Callable[[], bytes]


class SaveWriter:
    """One writer thread (started at the first save) for one loop's files. Call it as ``writer(what, path, data)``
    (the signature of :attr:`bridge.nodes.station_saves.StationSaves.writer`); :meth:`results` gives the outcomes
    since the last call as ``(what, error)``, ``error`` None for a save that succeeded. :meth:`close` writes what
    is still waiting and ends the thread (before a loop's final, synchronous save)."""

    def __init__(self, save: Save = save_atomic, name: str = "station-writer") -> None:
        self.save, self.name = save, name
        self.cond = threading.Condition()
        self.waiting: dict[Path, tuple[str, Payload]] = {}  # per file the latest bytes not yet being written
        self.done: list[tuple[str, OSError | None]] = []
        self.closed = False
        self.replaced = 0  # saves replaced by a later one of the same file before they were written
        self.thread: threading.Thread | None = None

    def __call__(self, what: str, path: Path, data: Payload) -> None:
        """Hand a save over (returns at once; a function is called on the writer's thread, or never when a later save
        of the same file replaced it first). After :meth:`close` it is written here, at once."""
        with self.cond:
            if not self.closed:
                if path in self.waiting:
                    self.replaced += 1
                    del self.waiting[path]  # re-inserted last: files are written in the order they were handed
                self.waiting[path] = (what, data)
                if self.thread is None:
                    self.thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                    self.thread.start()
                self.cond.notify_all()
                return
        self._write(what, path, data)

    def results(self) -> list[tuple[str, OSError | None]]:
        """The saves finished since the last call, in the order they finished: ``(what, error)``."""
        with self.cond:
            out, self.done = self.done, []
        return out

    def close(self) -> None:
        """Write what still waits, then end the thread (waits for the disk: an exit saves anyway)."""
        with self.cond:
            self.closed = True
            self.cond.notify_all()
            thread = self.thread
        if thread is not None:
            thread.join()

    def _run(self) -> None:
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.waiting or self.closed)
                if not self.waiting:
                    return  # closed, and everything written
                path = next(iter(self.waiting))
                what, data = self.waiting.pop(path)
            self._write(what, path, data)

    def _write(self, what: str, path: Path, data: Payload) -> None:
        error: OSError | None = None
        try:
            self.save(path, data if isinstance(data, bytes) else data())
        except OSError as exc:
            error = exc
        except Exception as exc:  # a bug must not end the thread silently: reported as a failed save
            log.exception("saving %s to %s failed", what, path)  # (an encoding's bug too)
            error = OSError(f"{type(exc).__name__}: {exc}")
        with self.cond:
            self.done.append((what, error))


__all__ = ["Payload", "Save", "SaveWriter"]
