"""What a station keeps across restarts, and how a failed save is reported (docs/ARCHITECTURE.md, "A person is in
charge" and "Threads and clocks"): the pair store every ``persist_every_s`` and the mission state whenever it
changed.

A save the tick asks for is a snapshot taken in the tick (:func:`snapshot`: the store's arrays copied, as the store
and the mission go on changing) handed to :attr:`StationSaves.writer` when the adapter gives one
(:class:`bridge.nodes.writer.SaveWriter`): its thread encodes it, tags it (:class:`bridge.nodes.station_tags.FileTags`)
and writes it, off the tick, and the outcome comes back through :meth:`StationSaves.saved`; else it is written at
once. A failure
(a full disk, permissions) never stops the loop: it is counted (``persist_failures``), kept in
:attr:`StationSaves.error` for the status (not ok, reason ``persist_failed``, the words in its text), logged, and
retried (the store at the next period, the mission state at the next tick); a save that succeeds again clears it.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from bridge.core import wire as M
from bridge.core.auth import KeyFileError
from bridge.core.paths import save_atomic
from bridge.nodes.mission_control import MissionControl
from bridge.nodes.station_status import StationCounters
from bridge.nodes.station_tags import FileTags
from transfer.store import PairStore

log = logging.getLogger("scmbridge.station")

#: a writer of saves off the tick: ``(what, path, data)``, ``what`` "store" or "control", ``data`` a function that
#: gives the tagged bytes of a snapshot (called once, on the writer's thread; :data:`bridge.nodes.writer.Payload`,
#: not imported: the core imports no threading)
Writer = Callable[[str, Path, bytes | Callable[[], bytes]], None]

T = TypeVar("T")


def snapshot(obj: T, depth: int = 2) -> T:
    """A copy of ``obj`` that the tick's later changes leave alone, taken cheaply: a shallow copy whose numpy arrays,
    lists and dicts are copies, and whose attributes that are objects with arrays of their own (the store's learned
    limits) are snapshots in turn, ``depth`` levels down. What it shares is only what is never changed in place (the
    bounds, numbers, strings, tuples) or what its encoding does not read (caches, the change watch)."""
    out = copy.copy(obj)
    for k, v in vars(out).items():
        if isinstance(v, np.ndarray):
            setattr(out, k, v.copy())
        elif isinstance(v, list | dict):
            setattr(out, k, copy.copy(v))
        elif (depth > 1 and hasattr(v, "__dict__") and not _frozen(v)
              and any(isinstance(a, np.ndarray) for a in vars(v).values())):
            setattr(out, k, snapshot(v, depth - 1))
    return out


def _frozen(obj: object) -> bool:
    """A frozen dataclass (the bounds): never changed in place, shared."""
    params = getattr(type(obj), "__dataclass_params__", None)
    return bool(params is not None and params.frozen)


class StationSaves:
    """One station's saves: its pair store to ``store_path`` each ``every`` seconds (:meth:`periodic`), its mission
    state to ``control_path`` (None: not kept) when the tick asks (:meth:`save`), and the final saves at exit
    (:meth:`persist`, :meth:`save_control`). Not thread-safe: the core's thread only (outcomes of the writer's
    thread come back through :meth:`saved`, called by the adapter on that thread)."""

    def __init__(self, store: PairStore, store_path: Path, control: MissionControl, control_path: Path | None,
                 counters: StationCounters, every: float, phase: float = 0.0) -> None:
        """``every``: the store's save period, s; ``phase`` (0 to 1): the second save comes ``(1 + phase) * every``
        after the first (at the first periodic tick), then every ``every``: the robots of a fleet that start
        together do not all save in the same tick."""
        self.store, self.store_path = store, Path(store_path)
        self.phase = float(phase)
        self.control, self.control_path = control, control_path
        self.counters, self.every = counters, every
        #: the adapter's writer of the tick's saves (see :data:`Writer`): it writes them off the tick and reports
        #: each outcome back through :meth:`saved`; None: saved at once
        self.writer: Writer | None = None
        self.error = ""  # the last save's failure in words ("" when the last one of each file succeeded)
        #: tags each file as this station's (bridge/nodes/station_tags.py); None: saved as they are
        self.tags: FileTags | None = None
        self.next_at: float | None = None  # the store's next save is due then (None: at the first periodic tick)
        self._keyed: set[Path] = set()  # the files whose key :meth:`save` has made or read on this thread

    def periodic(self, now: float) -> None:
        """The pair store's save when it is due (at the first periodic tick, then as :meth:`__init__` says)."""
        if self.next_at is None or now >= self.next_at:
            first = self.next_at is None
            self.save("store")
            self.next_at = now + self.every * (1.0 + self.phase if first else 1.0)

    def save(self, what: str) -> None:
        """A save the tick asks for (``what``: "store" or "control"): a snapshot taken now, handed to :attr:`writer`
        to be encoded, tagged and written on its thread; without a writer, saved at once."""
        if self.writer is None:
            self.persist() if what == "store" else self.save_control()
        elif what == "store":
            store, path = snapshot(self.store), self.store_path
            self._key_ready(path)
            self.writer("store", path, lambda: self._sealed("store", path, store.to_bytes()))
        elif self.control_path is not None:
            saved, path = self.control.saved(), self.control_path  # a new message (a snapshot of its own)
            self._key_ready(path)
            self.writer("control", path, lambda: self._sealed("control", path, M.encode(saved)))

    def _key_ready(self, path: Path) -> None:
        """The key that tags ``path`` made (or read) here at the file's first save, on the loop's thread: the
        writer threads of a process's stations, whose files share a directory and so a key, would otherwise race to
        make it (one station's file then tagged with a key another replaced). A key that cannot be had is left to
        the writer, whose seal fails again and is reported as a failed save."""
        if self.tags is None or path in self._keyed:
            return
        self._keyed.add(path)
        try:
            self.tags.key(path)
        except KeyFileError:
            pass

    def _sealed(self, kind: str, path: Path, data: bytes) -> bytes:
        return self.tags.seal(kind, path, data) if self.tags is not None else data

    def saved(self, what: str, error: OSError | None) -> bool:
        """A save that ended (at once, or on the adapter's writer thread), ``error`` None when it succeeded: a failure
        is counted, reported on the status and retried (the store at the next period, the mission state at the next
        tick). True: it succeeded."""
        if what == "store":
            return self._store_saved(error)
        if error is not None:
            self.counters.persist_failures += 1
            self.control.changed = True  # retried next tick
            self.error = f"mission state not saved: {error.strerror or error}"
        return error is None

    def persist(self) -> bool:
        """Save the store now (and at exit); a failure (disk full, permissions) is reported and retried at the next
        period. True: saved."""
        try:
            save_atomic(self.store_path, self._sealed("store", self.store_path, self.store.to_bytes()))
        except OSError as exc:
            return self._store_saved(exc)
        return self._store_saved(None)

    def save_control(self) -> None:
        """Keep the mission and its phase on disk now (a restart comes back to it, never running)."""
        if self.control_path is None:
            return
        try:
            save_atomic(self.control_path, self._sealed("control", self.control_path, M.encode(self.control.saved())))
        except OSError as exc:
            self.saved("control", exc)

    def _store_saved(self, error: OSError | None) -> bool:
        if error is not None:
            self.counters.persist_failures += 1
            self.error = f"pair store not saved: {error.strerror or error}"
            log.error("%s (%s); driving on, retrying in %.0f s", self.error, self.store_path, self.every)
            return False
        if self.error:
            log.info("pair store saved again to %s", self.store_path)
        self.error = ""
        return True


__all__ = ["StationSaves", "Writer", "snapshot"]
