"""The robot's estop latch on its disk (docs/ARCHITECTURE.md, section 6: "The estop latch fails safe").

The driver host latches its gate in memory at once (:mod:`bridge.nodes.driver_host`); this module keeps that latch
on disk so it survives a restart or a reboot, and fails safe: the first start in a state directory writes an install
marker holding a per-robot key and a released latch; every latch saved carries a keyed tag under that key
(:func:`bridge.core.auth.record_tag`); at start only a latch whose tag verifies says released (:func:`inspect_latch`).
A latched save that fails removes the old file, so a restart finds it missing beside the marker and starts latched.

Pieces: :class:`Latch` (the record), the file helpers (:func:`latch_file`, :func:`latch_marker`, :func:`read_marker`,
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
from bridge.core.auth import KEY_BYTES, read_key_file, record_tag, record_tag_ok
from bridge.core.paths import save_atomic, state_dir

log = logging.getLogger("scmbridge.driver")  # the driver host's log: the latch is its own


class Latch(msgspec.Struct, kw_only=True):
    """The estop latch as kept on the robot's disk. ``tag``: :func:`bridge.core.auth.record_tag` over the other
    three fields under the robot's latch key (:func:`latch_marker`), so a file this host did not write reads as
    latched (:func:`inspect_latch`); empty in memory and in a file older than the tag."""

    latched: bool
    source: str = ""
    reason: str = ""
    tag: bytes = b""


def latch_file(robot: str) -> Path:
    """Where a robot's estop latch is kept (the state directory survives restarts and reboots)."""
    return state_dir() / f"estop-{robot}.bin"


def latch_marker(path: Path) -> Path:
    """The install marker beside the latch file ``path`` (``estop-<robot>.installed``): written atomically at the
    first start in a state directory, and never again. It holds the robot's latch key (32 random bytes as hex, mode
    0600), which signs every latch the host saves; its presence says this directory has an estop history, so a
    latch file missing beside it counts as latched."""
    return path.with_name(path.stem + ".installed")


def _unsigned(latch: Latch) -> bytes:
    return M.encode(Latch(latched=latch.latched, source=latch.source, reason=latch.reason))


def sign_latch(key: bytes, latch: Latch) -> Latch:
    """``latch`` with its tag under ``key`` (what :class:`LatchWriter` saves)."""
    return Latch(latched=latch.latched, source=latch.source, reason=latch.reason,
                 tag=record_tag(key, _unsigned(latch)))


def read_marker(path: Path) -> bytes | None:
    """The latch key in the install marker ``path``; None if there is none. Raises ValueError (a
    :class:`bridge.core.auth.KeyProblem`) for a marker that is not a key or that others may read (a key others know
    signs releases for them), OSError for one unreadable: the checks of every key file (:func:`read_key_file`)."""
    try:
        return read_key_file(path)
    except FileNotFoundError:
        return None


def inspect_latch(path: Path, key: bytes | None = None) -> tuple[Latch, str]:
    """The latch a host starting now would take from ``path``, and the problem that made it latched ("" when the
    file says it as this host saved it). ``key``: the latch key (None: read from :func:`latch_marker`).

    Fail safe: only a latch file whose tag verifies under the robot's key says released; missing beside the
    install marker, unreadable, unsigned or forged, it is latched (the source says which). No marker and no latch
    file: this state directory has never seen an estop (a first start: released; the caller writes the marker).

    Why a keyed tag (and not only "a release must name the latch it releases"): the threat found was a
    ``released`` file written by someone else (or left by another state directory, or by an older version without
    tags); without the key nobody makes a tag that verifies. What it cannot stop: whoever can read the marker (this
    robot's user, root) can sign, and an older released file of this same host, copied back, verifies. The state
    directory is the host's alone (0700, ``scmbridge doctor`` checks it) and must stay the same across restarts
    (``SCMBRIDGE_STATE_DIR``): a host given an empty one cannot know an estop was latched elsewhere, so its start
    log and ``doctor`` say "first start in this state directory: no estop history"."""
    marker = latch_marker(path)
    marker_problem = ""
    if key is None:
        try:
            key = read_marker(marker)
        except (OSError, ValueError) as exc:
            marker_problem = f"latch key {marker} unusable: {getattr(exc, 'strerror', None) or exc}"
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        if key is None and not marker_problem and not os.path.lexists(marker):
            return Latch(latched=False), ""  # never latched in this state directory
        return (Latch(latched=True, source="missing latch file", reason=f"{path} is missing"),
                f"latch file {path} missing (this state directory has an estop history: {marker.name})")
    except OSError as exc:
        problem = f"latch file {path} unreadable: {exc.strerror or exc}"
        return Latch(latched=True, source="unreadable latch file", reason=problem[:200]), problem
    try:
        saved = M.decode(data, Latch)
    except M.MessageError as exc:
        problem = f"latch file {path} unreadable: {exc}"
        return Latch(latched=True, source="unreadable latch file", reason=problem[:200]), problem
    plain = Latch(latched=saved.latched, source=saved.source, reason=saved.reason)
    if key is not None and saved.tag and record_tag_ok(key, _unsigned(saved), saved.tag):
        return plain, ""
    if saved.latched:  # latched whoever wrote it
        return plain, ""
    why = (marker_problem or f"no latch key ({marker.name} missing)" if key is None
           else "not signed by this host" if not saved.tag else "its tag does not verify (written by someone else)")
    problem = f"latch file {path} says released but {why}"
    return Latch(latched=True, source="unverified latch file", reason=problem[:200]), problem


def read_latch(path: Path, key: bytes | None = None) -> Latch:
    """The latch a host starting now would take (:func:`inspect_latch`), without its tag; a problem is said in the
    log (the host starts latched: release it with scmbridge estop --release)."""
    latch, problem = inspect_latch(path, key)
    if problem:
        log.error("estop %s: starting latched; release it with scmbridge estop --release", problem)
    return latch


class LatchWriter:
    """Keeps the estop latch on disk off the control path: :meth:`submit` hands over the latch and returns at once;
    one thread saves it (``save``: write, fsync, rename, fsync the directory; milliseconds on a fast disk, seconds on
    a slow or failing one). The latest latch wins: what is submitted while a save runs is saved once, after it.
    ``done(latch, error)`` is called in that thread after each save with None or what went wrong: the one place where
    a save's result is known. A stop never waits for the disk (measured: with each fsync delayed 0.5 s the first
    stop came 1.02 s after the estop while the save ran under the lock the loop needs); a confirmation of the latch
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
            if self.saved >= self.submitted:
                return False
            self.waiters.append((self.submitted, fn))
            return True

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
        self.key = b""  # signs every latch saved (the install marker holds it)
        self.marker_saved = False  # the install marker is on disk (else the next latch save writes it first)
        self.fresh_state = False  # first start in this state directory: no estop history
        self.writer = LatchWriter(path, self._saved, self._save_file) if path is not None else None

    def open(self) -> Latch:
        """The saved latch (:func:`inspect_latch`: anything but a release this host signed is latched), after making
        sure the install marker is on disk; at the first start in a state directory write it and a released latch
        (marker first: a crash between the two leaves a marker without a latch file, which reads latched). These
        writes are the start's, with :func:`save_atomic` (a failure is logged; the first latch save tries the
        marker again). Released when kept in memory only."""
        path = self.path
        if path is None:
            return Latch(latched=False)
        marker = latch_marker(path)
        self.fresh_state = not os.path.lexists(marker) and not os.path.lexists(path)
        try:
            key = read_marker(marker)
        except (OSError, ValueError):
            key = None  # inspect_latch says why, and the latch reads latched
        saved = read_latch(path, key)
        self.marker_saved = key is not None
        self.key = key if key is not None else secrets.token_bytes(KEY_BYTES)
        log.info("estop latch %s (state directory %s)", path, path.parent)
        if self.fresh_state:
            log.warning("first start in this state directory: no estop history (%s); the state directory must stay "
                        "the same across restarts (SCMBRIDGE_STATE_DIR): a host started with another one cannot know "
                        "an estop latched in this one", path.parent)
        try:
            if not self.marker_saved:
                save_atomic(marker, self.key.hex().encode() + b"\n")
                self.marker_saved = True
            if self.fresh_state:
                save_atomic(path, M.encode(sign_latch(self.key, Latch(latched=False, reason="first start"))))
        except OSError as exc:
            log.error("estop latch: cannot write %s (%s): an estop is kept in memory only until a save succeeds",
                      marker if not self.marker_saved else path, exc.strerror or exc)
        return saved

    def submit(self, latched: bool, source: str, reason: str) -> None:
        """Have this latch kept on disk, signed (returns at once: the caller may hold its lock, to keep the order of
        the changes; the latest submitted wins)."""
        if self.writer is not None:
            self.writer.submit(sign_latch(self.key, Latch(latched=latched, source=source, reason=reason)))

    def defer(self, fn: Callable[[], None]) -> bool:
        """:meth:`LatchWriter.defer`: True when ``fn`` will run once every latch submitted so far is saved (or its
        save failed); False when nothing is waiting (``fn`` is not called)."""
        return self.writer is not None and self.writer.defer(fn)

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
            dfd = os.open(path.parent, os.O_DIRECTORY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError as exc:
            return f"the old latch file could not be removed either ({exc.strerror or exc}): a restart may read it"
        return ""

    def _save_file(self, path: Path, data: bytes) -> None:
        """The writer's save: the install marker first if it is not on disk yet, then the latch."""
        if not self.marker_saved:
            self.saver(latch_marker(path), self.key.hex().encode() + b"\n")
            self.marker_saved = True
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
