"""The station's files carry a tag like the estop latch (docs/SECURITY.md, "The station's files"): the pair store
and the mission state are saved as ``FILE_MAGIC + tag + payload``, the tag a keyed BLAKE2b
(:func:`bridge.core.auth.record_tag`) over the file's kind and payload under a station key kept in a record outside
the state directory (:func:`bridge.nodes.latch_record.record_dir`, one key per directory of files).

Found by a hostile test: with the station down, its mission file rewritten to a path behind the robot was driven
after ``mission resume``, and status never said it had changed; a crafted pair store (mirrored yaw-rate pairs) cut
the obstacle clearance from 0.29 to 0.16 m. A file whose tag does not verify is refused (kept aside, the reason
said); an untagged file (written by an older version) is taken only at the start that makes the key, and is tagged
at its next save. What remains: whoever may write the record directory (this station's user, root) can tag.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from bridge.core.auth import KeyFileError, create_key, load_key, record_tag, record_tag_ok
from bridge.nodes.latch_record import record_dir

FILE_MAGIC = b"\xa5\x04"  # a station file tagged by its station, version 1
TAG = 16


def key_file(path: Path) -> Path:
    """The key that tags the files in ``path``'s directory."""
    where = hashlib.blake2b(os.path.realpath(Path(path).parent).encode(), digest_size=8).hexdigest()
    return record_dir() / f"station-{where}.key"


#: the key files this process made: where an untagged file of an older version is taken, at this start only
_MADE: set[Path] = set()


class FileTags:
    """Tags the station's files and checks them (keys read, or made, once per directory)."""

    def __init__(self) -> None:
        self.keys: dict[Path, bytes] = {}
        self.fresh = _MADE

    def key(self, path: Path) -> bytes:
        kf = key_file(path)
        if kf not in self.keys:
            try:
                self.keys[kf] = load_key(kf, "station")
            except KeyFileError:
                if os.path.lexists(kf):  # a file that cannot be used (raises again), or one made since by another
                    self.keys[kf] = load_key(kf, "station")  # robot of this host (read it)
                else:
                    self.keys[kf], made = create_key(kf, "station")
                    if made:
                        self.fresh.add(kf)
        return self.keys[kf]

    def seal(self, kind: str, path: Path, data: bytes) -> bytes:
        """``data`` tagged as the station's ``kind`` file at ``path``."""
        return FILE_MAGIC + record_tag(self.key(path), kind.encode() + b"\0" + data) + data

    def open(self, kind: str, path: Path, blob: bytes) -> tuple[bytes | None, str]:
        """``(payload, "")`` when ``blob`` is the station's own ``kind`` file at ``path``, else ``(None, why)``."""
        try:
            key = self.key(path)
        except KeyFileError as exc:
            return None, f"the station's file key is unusable ({exc})"
        if blob[:len(FILE_MAGIC)] != FILE_MAGIC:
            if key_file(path) in self.fresh:
                return blob, ""  # an older version's file, at the start that made the key: tagged at its next save
            return None, "it carries no tag of this station (written by someone else, or by an older version)"
        tag, data = blob[len(FILE_MAGIC):len(FILE_MAGIC) + TAG], blob[len(FILE_MAGIC) + TAG:]
        if not record_tag_ok(key, kind.encode() + b"\0" + data, tag):
            return None, "its tag does not verify (changed while the station was down, or another station's)"
        return data, ""


def file_problem(kind: str, path: Path) -> str:
    """What a station starting now would say against its ``kind`` file at ``path`` ("" when it is its own), without
    making a key (``scmbridge doctor``)."""
    from bridge.core.paths import STORE_FILE, read_bounded

    kf = key_file(path)
    try:
        blob = read_bounded(Path(path), STORE_FILE)
        key = load_key(kf, "station") if os.path.lexists(kf) else None
    except (OSError, KeyFileError) as exc:
        return f"cannot be checked: {exc}"
    if key is None:
        return f"no station key ({kf} missing): the next station start refuses it"
    tags = FileTags()
    tags.keys[kf] = key
    tags.fresh = set()
    return tags.open(kind, Path(path), blob)[1]


def untagged(blob: bytes) -> bytes:
    """The payload of a station file, its tag not checked (for tools that only look at a file: ``scmbridge pairs
    show``, a demo's report); an untagged file as it is."""
    return blob[len(FILE_MAGIC) + TAG:] if blob[:len(FILE_MAGIC)] == FILE_MAGIC else blob


def read_store(path: Path):
    """The pair store in the station file ``path``, to look at (its tag not checked: never to drive with)."""
    from bridge.core.paths import STORE_FILE, read_bounded
    from transfer.store import PairStore

    return PairStore.from_bytes(untagged(read_bounded(Path(path), STORE_FILE)))


__all__ = ["FILE_MAGIC", "FileTags", "file_problem", "key_file", "read_store", "untagged"]
