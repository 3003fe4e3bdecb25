"""The robot's estop latch on its disk (docs/ARCHITECTURE.md, section 6: "The estop latch fails safe").

The driver host latches its gate in memory at once (:mod:`bridge.nodes.driver_host`); this module keeps that latch
on disk so it survives a restart or a reboot, and fails safe: the first start in a state directory writes a record
outside it holding a per-robot key and a count (:mod:`bridge.nodes.latch_record`), an install marker beside the
latch holding the key's fingerprint, and a released latch; every latch saved carries its count and a keyed tag
under that key (:func:`bridge.core.auth.record_tag`); at start only a latch whose tag verifies, whose count is the
record's and whose marker is the record's says released (:func:`inspect_latch`). A latched save that fails removes
the old file, so a restart finds it missing beside the marker and starts latched.

Pieces: :class:`Latch` (the record), the file helpers (:func:`latch_file`, :func:`latch_marker`,
:func:`inspect_latch`, :func:`read_latch`, :func:`sign_latch`), :class:`LatchWriter` (one thread that saves off the
control path) and :class:`LatchStore` (one robot's latch: opened at start, saved through the writer, forgotten after
a latched save failed; what a save came to is handed to the host as a :class:`SaveResult`). No Zenoh; the host's
lock is never taken here (the host applies a :class:`SaveResult` to its gate under its own lock).
"""

from __future__ import annotations

import logging
import os
import secrets
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgspec

from bridge.core import wire as M
from bridge.core.auth import KEY_BYTES, record_tag, record_tag_ok
from bridge.core.paths import SMALL_FILE, fsync_dir, read_bounded, save_atomic, state_dir
from bridge.nodes.latch_record import (
    Record,
    fingerprint,
    marker_text,
    read_marker_text,
    read_record,
    record_file,
)

log = logging.getLogger("scmbridge.driver")  # the driver host's log: the latch is its own


class Latch(msgspec.Struct, kw_only=True):
    """The estop latch as kept on the robot's disk. ``tag``: :func:`bridge.core.auth.record_tag` over the other
    fields under the robot's latch key (kept in its record, :mod:`bridge.nodes.latch_record`), so a file this host
    did not write reads as latched (:func:`inspect_latch`); empty in memory and in a file older than the tag.
    ``count``: how many latches this host had saved with it (the record keeps the last), so an older file copied
    back reads latched."""

    latched: bool
    source: str = ""
    reason: str = ""
    tag: bytes = b""
    count: int = 0


def latch_file(robot: str) -> Path:
    """Where a robot's estop latch is kept (the state directory survives restarts and reboots)."""
    return state_dir() / f"estop-{robot}.bin"


def latch_marker(path: Path) -> Path:
    """The install marker beside the latch file ``path`` (``estop-<robot>.installed``): written atomically at the
    first start in a state directory. It holds the fingerprint of the robot's latch key (the key itself is in the
    record, outside the state directory: :func:`bridge.nodes.latch_record.record_file`); its presence says this
    directory has an estop history, so a latch file missing beside it counts as latched."""
    return path.with_name(path.stem + ".installed")


def _unsigned(latch: Latch) -> bytes:
    return M.encode(Latch(latched=latch.latched, source=latch.source, reason=latch.reason, count=latch.count))


def sign_latch(key: bytes, latch: Latch) -> Latch:
    """``latch`` with its tag under ``key`` (what :class:`LatchWriter` saves)."""
    return Latch(latched=latch.latched, source=latch.source, reason=latch.reason, count=latch.count,
                 tag=record_tag(key, _unsigned(latch)))


def _latched(source: str, problem: str) -> tuple[Latch, str]:
    return Latch(latched=True, source=source, reason=problem[:200]), problem


def inspect_latch(path: Path) -> tuple[Latch, str]:
    """The latch a host starting now would take from ``path``, and the problem that made it latched ("" when the
    file says it as this host saved it).

    Fail safe: only a latch file whose tag verifies under the key of this state directory's record, whose count is
    the record's and whose install marker is the record's key's says released; anything else is latched (the
    source says which): missing beside the marker or the record, unreadable, unsigned or forged, copied back (an
    older count), a marker of another key. No record, no marker and no latch file: this state directory has never
    seen an estop (a first start: released; the caller writes them). A marker of an older version (holding the key
    itself) is taken as the record once (:class:`LatchStore` moves the key out).

    What it cannot stop: whoever may write the record directory and the state directory (this robot's user, root)
    can delete both, and the next start is a first start: the host's start log and ``doctor`` say "first start in
    this state directory: no estop history" (docs/SECURITY.md)."""
    marker, recfile = latch_marker(path), record_file(path)
    problems = []
    try:
        rec = read_record(recfile)
    except (OSError, ValueError) as exc:
        rec, problems = None, [f"estop record {recfile} unusable: {getattr(exc, 'strerror', None) or exc}"]
    try:
        mark = read_marker_text(marker)
    except (OSError, ValueError) as exc:
        mark = None
        problems.append(f"install marker {marker} unusable: {getattr(exc, 'strerror', None) or exc}")
    if rec is None and mark is not None and mark[1] is not None:
        rec = Record(mark[1], 0)  # an older version's marker: the key is in it (moved out at this start)
    elif mark is not None and rec is not None and mark[0] != fingerprint(rec.key):
        problems.append(f"install marker {marker} is of another key (replaced, or from another host)")
    elif mark is None and rec is not None and not problems:
        problems.append(f"install marker {marker} missing although this host has run in this state directory "
                        f"(its record {recfile}): deleted")
    try:
        data = read_bounded(path, SMALL_FILE)
    except FileNotFoundError:
        if rec is None and not problems and mark is None and not os.path.lexists(marker):
            return Latch(latched=False), ""  # never latched in this state directory
        why = "; ".join(problems) or f"this state directory has an estop history: {marker.name}"
        return _latched("missing latch file", f"latch file {path} missing ({why})")
    except OSError as exc:
        return _latched("unreadable latch file", f"latch file {path} unreadable: {exc.strerror or exc}")
    try:
        saved = M.decode(data, Latch)
    except M.MessageError as exc:
        return _latched("unreadable latch file", f"latch file {path} unreadable: {exc}")
    plain = Latch(latched=saved.latched, source=saved.source, reason=saved.reason)
    if saved.latched:  # latched whoever wrote it
        return plain, ""
    signed = rec is not None and saved.tag and record_tag_ok(rec.key, _unsigned(saved), saved.tag)
    if signed and rec.count and saved.count < rec.count:
        problems.append(f"it is older than the last latch this host saved (count {saved.count} < {rec.count}): "
                        "copied back, or a save that did not finish")
    if signed and not problems:
        return plain, ""
    if not problems:
        problems.append(f"no latch key (its record {recfile} missing)" if rec is None
                        else "not signed by this host" if not saved.tag
                        else "its tag does not verify (written by someone else)")
    return _latched("unverified latch file", f"latch file {path} says released but {'; '.join(problems)}")


def read_latch(path: Path) -> Latch:
    """The latch a host starting now would take (:func:`inspect_latch`), without its tag; a problem is said in the
    log (the host starts latched: release it with scmbridge estop --release)."""
    latch, problem = inspect_latch(path)
    if problem:
        log.error("estop %s: starting latched; release it with scmbridge estop --release", problem)
    return latch


class LatchWriter:
    """Keeps the estop latch on disk off the control path: :meth:`submit` hands over the latch and returns at once;
    one thread saves it (``save``: write, fsync, rename, fsync the directory; milliseconds on a fast disk, seconds on
    a slow or failing one). The latest latch wins: what is submitted while a save runs is saved once, after it.
    ``done(latch, error)`` is called in that thread after each save with None or what went wrong: the one place where
    a save's result is known. A stop never waits for the disk (with the save under the lock the loop needs, a slow fsync
    delays the stop by as long: docs/BENCHMARKS.md, "An estop on a slow disk"); a confirmation of the latch
    does (:meth:`defer`)."""

    def __init__(self, path: Path, done: Callable[[Latch, Exception | None], None],
                 save: Callable[[Path, bytes], None] = save_atomic) -> None:
        self.path, self.done, self.save = path, done, save
        self.cond = threading.Condition()
        self.pending: Latch | None = None
        self.submitted = self.saved = 0  # versions: every latch submitted up to ``saved`` was saved (or tried)
        self.waiters: list[tuple[int, Callable[[], None]]] = []
        self.closing = False
        self.thread = threading.Thread(target=self._run, name="latch-writer", daemon=True)
        self.thread.start()

    def submit(self, latch: Latch) -> None:
        """Save ``latch`` soon (never blocks on the disk: callers may hold the host's lock, to keep the order)."""
        with self.cond:
            self.pending = latch
            self.submitted += 1
            self.cond.notify_all()

    def defer(self, fn: Callable[[], None]) -> bool:
        """True: ``fn`` runs in the writer's thread once every latch submitted so far has been saved (or its save
        failed); False: nothing is waiting to be saved (``fn`` is not called: the caller goes on at once)."""
        with self.cond:
            if not self.saving():
                return False
            self.waiters.append((self.submitted, fn))
            return True

    def saving(self) -> bool:
        """Whether a latch submitted so far still waits for its save (or is being saved)."""
        with self.cond:  # (a re-entrant lock: :meth:`defer` asks under it)
            return self.saved < self.submitted

    def _run(self) -> None:
        while True:
            with self.cond:
                while self.pending is None and not self.closing:
                    self.cond.wait()
                if self.pending is None:
                    return
                latch, version, self.pending = self.pending, self.submitted, None
            error: Exception | None = None
            try:
                self.save(self.path, M.encode(latch))
            except Exception as exc:  # a full disk, a read-only file system, a bug: said and counted by done()
                error = exc
            try:
                self.done(latch, error)
            except Exception:
                log.exception("estop latch: handling the save's result failed")
            with self.cond:
                self.saved = version
                ready = [fn for v, fn in self.waiters if v <= version]
                self.waiters = [(v, fn) for v, fn in self.waiters if v > version]
                self.cond.notify_all()
            for fn in ready:
                try:
                    fn()
                except Exception:
                    log.exception("estop latch: answering after the save failed")

    def close(self, timeout: float) -> bool:
        """Save what is still pending, bounded by ``timeout`` s, and end the thread; False if it did not finish."""
        with self.cond:
            self.closing = True
            self.cond.notify_all()
        self.thread.join(timeout)
        return not self.thread.is_alive()


@dataclass(frozen=True, slots=True)
class SaveResult:
    """What one save of the latch came to (handed to the host in the writer's thread). ``error``: "" when saved,
    else what went wrong in words; ``text``: while the save has failed, what the host says on status and in a refused
    engage (reason ``latch_unsaved``); ``relatch``: a release that was not saved, so the host latches its gate again
    (memory never drives while the disk says latched)."""

    latch: Latch
    error: str = ""
    text: str = ""

    @property
    def saved(self) -> bool:
        return not self.error

    @property
    def relatch(self) -> bool:
        return not self.saved and not self.latch.latched


class LatchStore:
    """One robot's estop latch on disk: :meth:`open` at start (take the saved latch, write the install marker at
    the first start), :meth:`submit` at each change (signed, saved by the :class:`LatchWriter`'s thread),
    :meth:`defer` an answer until what was submitted is saved, :meth:`close` at exit. ``path`` None: kept in memory
    only (every method is then a no-op). ``done(result)`` is called in the writer's thread after each save (fail
    safe: a latched save that failed has already removed the old file, :meth:`forget`, when it is called).
    ``saver``: how a file is saved (atomically; a test slows it down or has it fail as a full disk does); the start's
    own writes (:meth:`open`) use :func:`save_atomic`."""

    def __init__(self, path: Path | None, done: Callable[[SaveResult], None],
                 saver: Callable[[Path, bytes], None] = save_atomic) -> None:
        self.path, self.done, self.saver = path, done, saver
        self.key = b""  # signs every latch saved (its record holds it, outside the state directory)
        self.count = 0  # the count of the last latch submitted (its record holds the last saved)
        self.record_saved = False  # the record is on disk
        self.marker_saved = False  # the install marker is on disk (else the next latch save writes it first)
        self.fresh_state = False  # first start in this state directory: no estop history
        self.writer = LatchWriter(path, self._saved, self._save_file) if path is not None else None

    def open(self) -> Latch:
        """The saved latch (:func:`inspect_latch`: anything but a release this host signed, as its record counts
        it, is latched), after making sure the record and the install marker are on disk and agree; at the first
        start in a state directory write them and a released latch (record, then marker, then latch: a crash
        between them reads latched). These writes are the start's, with :func:`save_atomic` (a failure is logged;
        the first latch save tries again). A marker of an older version, holding the key itself, has its key moved
        into the record and is rewritten as a fingerprint. Released when kept in memory only."""
        path = self.path
        if path is None:
            return Latch(latched=False)
        marker, recfile = latch_marker(path), record_file(path)
        try:
            rec = read_record(recfile)
            bad_record = False
        except (OSError, ValueError):
            rec, bad_record = None, True  # inspect_latch says why, and the latch reads latched
        try:
            mark = read_marker_text(marker)
        except (OSError, ValueError):
            mark = None
        self.fresh_state = (rec is None and not bad_record and not os.path.lexists(marker)
                            and not os.path.lexists(path))
        saved = read_latch(path)
        if rec is None and mark is not None and mark[1] is not None:
            rec = Record(mark[1], 0)  # an older version's marker: its key moves to the record
            self.record_saved = False
        else:
            self.record_saved = rec is not None
        self.key = rec.key if rec is not None else secrets.token_bytes(KEY_BYTES)
        self.count = rec.count if rec is not None else 0
        self.marker_saved = self.record_saved and mark is not None and mark == (fingerprint(self.key), None)
        log.info("estop latch %s (state directory %s, record %s)", path, path.parent, recfile)
        if self.fresh_state:
            log.warning("first start in this state directory: no estop history (%s, no record %s); the state "
                        "directory must stay the same across restarts (SCMBRIDGE_STATE_DIR): a host started with "
                        "another one cannot know an estop latched in this one", path.parent, recfile)
        try:
            if self.fresh_state:
                self.count = 1
            self._save_keys(save_atomic, self.count)
            if self.fresh_state:
                save_atomic(path, M.encode(sign_latch(self.key, Latch(latched=False, reason="first start",
                                                                      count=self.count))))
        except OSError as exc:
            log.error("estop latch: cannot write its record, marker or file (%s): an estop is kept in memory only "
                      "until a save succeeds", exc.strerror or exc)
        return saved

    def submit(self, latched: bool, source: str, reason: str) -> None:
        """Have this latch kept on disk, signed and counted (returns at once: the caller may hold its lock, to keep
        the order of the changes; the latest submitted wins)."""
        if self.writer is not None:
            self.count += 1
            self.writer.submit(sign_latch(self.key, Latch(latched=latched, source=source, reason=reason,
                                                          count=self.count)))

    def defer(self, fn: Callable[[], None]) -> bool:
        """:meth:`LatchWriter.defer`: True when ``fn`` will run once every latch submitted so far is saved (or its
        save failed); False when nothing is waiting (``fn`` is not called)."""
        return self.writer is not None and self.writer.defer(fn)

    def saving(self) -> bool:
        """:meth:`LatchWriter.saving`: whether a latch submitted so far still waits for its save."""
        return self.writer is not None and self.writer.saving()

    def close(self, timeout: float) -> bool:
        """Let a save still under way finish (bounded by ``timeout`` s); False if it did not."""
        return self.writer is None or self.writer.close(timeout)

    def forget(self) -> str:
        """After a latched save failed: remove the latch file on disk (possible on a full disk; it may say
        released), so a restart finds it missing beside the install marker and starts latched. Returns what a
        restart would do, in words, when that cannot be made sure."""
        path = self.path
        if path is None:
            return ""
        if not self.marker_saved:
            return "no install marker on disk either: a restart would not know of this estop"
        try:
            path.unlink(missing_ok=True)
            fsync_dir(path.parent)
        except OSError as exc:
            return f"the old latch file could not be removed either ({exc.strerror or exc}): a restart may read it"
        return ""

    def _save_keys(self, saver: Callable[[Path, bytes], None], count: int) -> None:
        """The record (the key and ``count``) and, if it is not on disk yet, the install marker (the key's
        fingerprint): the record first, so a latch never names a count its record has not reached."""
        path = self.path
        assert path is not None
        saver(record_file(path), Record(self.key, count).encode())
        self.record_saved = True
        if not self.marker_saved:
            saver(latch_marker(path), marker_text(self.key))
            self.marker_saved = True

    def _save_file(self, path: Path, data: bytes) -> None:
        """The writer's save: the record (and the install marker if it is not on disk yet), then the latch."""
        self._save_keys(self.saver, M.decode(data, Latch).count)
        self.saver(path, data)

    def _saved(self, latch: Latch, error: Exception | None) -> None:
        """The writer's result, made fail safe before the host hears it: a latched save that failed removes the old
        file first (:meth:`forget`)."""
        if error is None:
            self.done(SaveResult(latch))
            return
        why = getattr(error, "strerror", None) or str(error)
        if latch.latched:
            text = f"estop latched but NOT saved to {self.path}: {why}; engage refused until it is saved"
            restart = self.forget()
        else:
            text = (f"estop release NOT saved to {self.path}: {why}; latched again, engage refused until a "
                    "release is saved")
            restart = ""
        self.done(SaveResult(latch, error=why, text=text))
        log.error("%s%s", text, f" ({restart})" if restart else "")
