"""Where a node keeps what must survive a restart (state: the pair store, the estop latch, the mission) and what it
may rebuild (cache: compiled code), and how it writes a file so a crash or a full disk never leaves it torn.

State: ``$SCMBRIDGE_STATE_DIR``, else systemd's ``$STATE_DIRECTORY`` (``StateDirectory=``), else
``$XDG_STATE_HOME/scmbridge`` (``~/.local/state/scmbridge``). Cache: ``$SCMBRIDGE_CACHE_DIR``, else
``$CACHE_DIRECTORY`` (``CacheDirectory=``), else ``$XDG_CACHE_HOME/scmbridge`` (``~/.cache/scmbridge``). Never the
working directory: two services started in one directory must not share a file by accident.
"""

from __future__ import annotations

import _thread  # only the calling thread's number (the station core starts no thread)
import errno
import os
import stat
import time
from pathlib import Path


def _first(value: str) -> str:
    """systemd passes several directories colon-separated; the first is this unit's own."""
    return value.split(":")[0]


def state_dir() -> Path:
    """The directory for files that must survive a restart (see the module docstring)."""
    for var in ("SCMBRIDGE_STATE_DIR", "STATE_DIRECTORY"):
        if os.environ.get(var):
            return Path(_first(os.environ[var]))
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "scmbridge"


def cache_dir() -> Path:
    """The directory for files that can be rebuilt (see the module docstring)."""
    for var in ("SCMBRIDGE_CACHE_DIR", "CACHE_DIRECTORY"):
        if os.environ.get(var):
            return Path(_first(os.environ[var]))
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "scmbridge"


def _make_private_dirs(directory: Path) -> None:
    """Create ``directory`` and its missing parents, each 0700 (``mkdir -p`` would give the parents the umask's)."""
    missing = []
    d = directory
    while not d.exists():
        missing.append(d)
        if d.parent == d:
            break
        d = d.parent
    for d in reversed(missing):
        try:
            d.mkdir(mode=0o700)
        except FileExistsError:  # made meanwhile by another process
            continue
        os.chmod(d, 0o700)  # mkdir's mode goes through the umask


def temporary_name(path: Path) -> Path:
    """Where :func:`save_atomic` writes ``path``'s content before the rename: beside it, hidden, named by this process
    and this thread, so two threads saving one file at once (two robots of one station host making their shared
    key) never write into, or rename away, each other's temporary file."""
    return path.with_name(f".{path.name}.{os.getpid()}.{_thread.get_ident()}.tmp")


def save_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` so that ``path`` holds either the old or the new content, never a torn file (write, fsync,
    rename, fsync the directory); on failure (a full disk) the temporary file is removed and the error raised.

    What a node keeps is private to its user: the file is 0600 whatever the umask (a key, the estop latch, the pairs
    a station learns from), and the directories it creates are 0700. A directory that exists is left as its owner
    set it (the shipped systemd units ask for ``StateDirectoryMode=0700``)."""
    path = Path(path)
    _make_private_dirs(path.parent)
    tmp = temporary_name(path)
    try:
        _write_private(tmp, os.O_TRUNC, data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def fsync_dir(directory: Path) -> None:
    """Make a file's creation, rename or removal in ``directory`` durable (fsync the directory itself)."""
    dfd = os.open(directory, os.O_DIRECTORY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


#: what ``link(2)`` says on a filesystem without hard links (FAT, some network and FUSE filesystems)
_NO_LINKS = frozenset({errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EMLINK})


def _write_private(path: Path, flag: int, data: bytes) -> None:
    """Create ``path`` (``flag``: ``O_TRUNC`` or ``O_EXCL``) mode 0600 whatever the umask, write ``data``, fsync."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | flag | getattr(os, "O_CLOEXEC", 0), 0o600)
    with open(fd, "wb") as f:
        os.fchmod(f.fileno(), 0o600)  # also a stale temporary file left by a crash with other bits
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def save_new(path: Path, data: bytes) -> bool:
    """Write ``data`` to ``path`` only if there is no file there yet, whole or not at all, as :func:`save_atomic`
    writes (private, fsynced): True if this call wrote it, False if one was there already (left as it is). Of
    several processes or threads creating one file at once exactly one writes it (the complete temporary file is
    hard-linked into place, which fails if the name exists); the others then read what it wrote. On a filesystem
    without hard links the file is created exclusively and written in place: still one writer, but a reader at that
    very moment may find it empty."""
    path = Path(path)
    _make_private_dirs(path.parent)
    tmp = temporary_name(path)
    try:
        _write_private(tmp, os.O_TRUNC, data)
        try:
            os.link(tmp, path)
        except FileExistsError:
            return False
        except OSError as exc:
            if exc.errno not in _NO_LINKS:
                raise
            try:
                _write_private(path, os.O_EXCL, data)
            except FileExistsError:
                return False
    finally:
        tmp.unlink(missing_ok=True)
    fsync_dir(path.parent)
    return True


def quarantine(path: Path) -> Path:
    """Move a file that cannot be used aside (``NAME.corrupt-<unix time>`` beside it): kept for a person to look at,
    never lost and never read again; returns where it went."""
    path = Path(path)
    aside = path.with_name(path.name + f".corrupt-{int(time.time())}")
    os.replace(path, aside)
    return aside


#: the largest key, marker or latch file read (a key is 65 bytes)
SMALL_FILE = 4096
#: the largest configuration or mission file read
TEXT_FILE = 1 << 20
#: the largest pair store read
STORE_FILE = 1 << 28


class NotAFile(OSError):
    """What was to be read is not a regular file, or is larger than it may be (a FIFO, a device such as /dev/zero,
    a directory, a file grown without bound)."""


def read_bounded(path: Path, limit: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them, else :class:`NotAFile` (never blocks on
    a FIFO: it is opened non-blocking and checked on its descriptor before a byte is read; never reads a device or
    a file larger than ``limit`` without bound). FileNotFoundError when there is none, as :func:`open`."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotAFile(f"{path} is not a regular file")
        if st.st_size > limit:
            raise NotAFile(f"{path} is larger than {limit} bytes ({st.st_size})")
        chunks, size = [], 0
        while True:
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
            if size > limit:
                raise NotAFile(f"{path} is larger than {limit} bytes (it grew while read)")
        return b"".join(chunks)
    finally:
        os.close(fd)
