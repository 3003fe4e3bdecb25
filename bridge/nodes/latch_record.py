"""Where a driver host keeps what makes its estop latch hold against its own state files: the latch key and the
count of the latch last saved, in a record *outside* the state directory (docs/SECURITY.md, "The estop latch";
docs/ARCHITECTURE.md section 6, "The estop latch fails safe").

Found by a hostile test: with the key in the install marker beside the latch, whoever read it signed a release;
a marker replaced by one's own key, an older released latch copied back, or marker and latch deleted together
(the host then believed it was a first start) each let the robot drive after a restart. So:

- the record (:func:`record_file`) holds the key and the count of the last latch saved; it lives in another
  directory (:func:`record_dir`), named after the state directory it belongs to, and is written before each latch;
- the install marker beside the latch holds only the key's fingerprint (:func:`fingerprint`): it says this state
  directory has an estop history and which key it belongs to, and signs nothing;
- a latch names its count: a released latch older than the record's count was copied back (or its save did not
  finish) and reads latched; a record present with neither latch nor marker says they were deleted: latched.

What remains: whoever may write both directories (this robot's user, root) can delete both, and the host then
starts as a first start, saying so in its log and in ``scmbridge doctor``. Pure apart from reading files.
"""

from __future__ import annotations

import hashlib
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from bridge.core.auth import KEY_BYTES
from bridge.core.paths import SMALL_FILE, read_bounded

HEAD = "scmbridge estop record 1"
MARKER_HEAD = "fingerprint"


def record_dir() -> Path:
    """The directory of the records, not the state directory: ``$SCMBRIDGE_RECORD_DIR``, else the second directory
    systemd passes in ``$STATE_DIRECTORY`` (``StateDirectory=scmbridge scmbridge-record``), else
    ``$XDG_DATA_HOME/scmbridge/records`` (``~/.local/share/scmbridge/records``)."""
    if os.environ.get("SCMBRIDGE_RECORD_DIR"):
        return Path(os.environ["SCMBRIDGE_RECORD_DIR"])
    dirs = os.environ.get("STATE_DIRECTORY", "").split(":")
    if len(dirs) > 1 and dirs[1]:
        return Path(dirs[1])
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "scmbridge" / "records"


def record_file(latch: Path) -> Path:
    """The record of the latch file ``latch``: its name and a hash of its state directory's real path (a host
    started with another state directory has another record)."""
    where = hashlib.blake2b(os.path.realpath(latch.parent).encode(), digest_size=8).hexdigest()
    return record_dir() / f"{latch.stem}-{where}.record"


def fingerprint(key: bytes) -> str:
    """What the install marker holds of the key: a hash it cannot be signed with."""
    return hashlib.blake2b(key, digest_size=16, person=b"scm-latch-fp").hexdigest()


@dataclass(frozen=True)
class Record:
    """The latch key and the count of the last latch saved."""

    key: bytes
    count: int

    def encode(self) -> bytes:
        return f"{HEAD}\n{self.key.hex()}\n{self.count}\n".encode()


def _private_text(path: Path) -> str:
    """The text of ``path``, a regular file of the owner alone, bounded (ValueError otherwise)."""
    data = read_bounded(path, SMALL_FILE)
    if stat.S_IMODE(path.stat().st_mode) & 0o077:
        raise ValueError(f"{path} is readable by others")
    try:
        return data.decode("ascii")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not text") from None


def read_record(path: Path) -> Record | None:
    """The record in ``path``; None if there is none. ValueError when it is not one, OSError when unreadable."""
    try:
        lines = _private_text(path).split("\n")
    except FileNotFoundError:
        return None
    try:
        if lines[0] != HEAD:
            raise ValueError
        key, count = bytes.fromhex(lines[1]), int(lines[2])
    except (IndexError, ValueError):
        raise ValueError(f"{path}: not an estop record") from None
    if len(key) != KEY_BYTES or count < 0:
        raise ValueError(f"{path}: not an estop record")
    return Record(key, count)


def marker_text(key: bytes) -> bytes:
    """The install marker's content for ``key``."""
    return f"{MARKER_HEAD} {fingerprint(key)}\n".encode()


def read_marker_text(path: Path) -> tuple[str, bytes | None] | None:
    """``(fingerprint, key)`` of the install marker ``path`` (``key`` set only for a marker of an older version,
    which held the key itself); None if there is none. ValueError when it is neither, OSError when unreadable."""
    try:
        text = _private_text(path).strip()
    except FileNotFoundError:
        return None
    if text.startswith(MARKER_HEAD + " "):
        fp = text[len(MARKER_HEAD) + 1:]
        if len(fp) == 32 and all(c in "0123456789abcdef" for c in fp):
            return fp, None
    else:
        try:
            key = bytes.fromhex(text)
        except ValueError:
            key = b""
        if len(key) == KEY_BYTES:
            return fingerprint(key), key
    raise ValueError(f"{path}: not an install marker")


__all__ = ["Record", "fingerprint", "marker_text", "read_marker_text", "read_record", "record_dir", "record_file"]
