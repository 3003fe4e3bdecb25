"""Authenticated datagrams for links whose medium carries no authentication of its own (the UDP shim).

Pinning a peer's address and port is not authentication: anyone on the segment can send from it. Each datagram is
``MAGIC + tag + payload``, the tag a keyed BLAKE2b (16 bytes) over the magic and the payload (the wire message,
which carries the sender's epoch and seq: a replay is then refused by the seq gate). Both ends read one key file
(32 random bytes, hex, mode 0600) made by ``scmbridge keys udp --robot R`` in the state directory; a datagram
whose tag does not verify is counted and dropped by the receiver. Pure apart from reading and writing key files.
The same tags, under a magic of their own (:func:`record_tag`), mark records a node keeps on its disk and must know
it wrote itself (the driver host's estop latch).

Session datagrams (the UDP shim's commands, drivers/udp.py has the protocol): ``SESSION_MAGIC + tag + boot + echo +
payload``, ``boot`` the receiver's boot nonce and ``echo`` a reading of the receiver's own clock (microseconds), both
unsigned 64-bit big-endian, the tag covering the magic, both and the payload. The receiver checks ``boot`` against
its current one and ``echo`` against its clock, so nothing sealed before its reboot, or long ago, is obeyed.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import struct
from pathlib import Path

from bridge.core.errors import UsageError
from bridge.core.paths import SMALL_FILE, NotAFile, read_bounded, save_atomic, save_new, state_dir

MAGIC = b"\xa5\x01"  # format and version of an authenticated datagram
TAG_BYTES = 16
KEY_BYTES = 32
OVERHEAD = len(MAGIC) + TAG_BYTES


class KeyFileError(UsageError):
    """A key file that is missing, unreadable, malformed or readable by others: one line, the fix named."""


SESSION_MAGIC = b"\xa5\x02"  # a session datagram (the receiver's boot nonce and clock echoed), version 1
RECORD_MAGIC = b"\xa5\x03"  # a record a node keeps on its own disk (the estop latch), version 1
_SESSION = struct.Struct(">QQ")
SESSION_OVERHEAD = len(SESSION_MAGIC) + TAG_BYTES + _SESSION.size
U64_MAX = 2**64 - 1


def _tag(key: bytes, payload: bytes, magic: bytes = MAGIC) -> bytes:
    return hashlib.blake2b(magic + payload, key=key, digest_size=TAG_BYTES).digest()


def seal_session(key: bytes, boot: int, echo_us: int, payload: bytes) -> bytes:
    """The session datagram carrying ``payload`` for a receiver whose boot nonce is ``boot``, echoing its clock
    reading ``echo_us`` (both clamped to unsigned 64 bits), with its tag over everything."""
    body = _SESSION.pack(min(max(int(boot), 0), U64_MAX), min(max(int(echo_us), 0), U64_MAX)) + payload
    return SESSION_MAGIC + _tag(key, body, SESSION_MAGIC) + body


def open_session(key: bytes, datagram: bytes) -> tuple[int, int, bytes] | None:
    """``(boot, echo_us, payload)`` if ``datagram`` is a session datagram sealed with ``key``, else None."""
    if len(datagram) < SESSION_OVERHEAD or datagram[: len(SESSION_MAGIC)] != SESSION_MAGIC:
        return None
    tag, body = datagram[len(SESSION_MAGIC):len(SESSION_MAGIC) + TAG_BYTES], datagram[len(SESSION_MAGIC) + TAG_BYTES:]
    if not hmac.compare_digest(tag, _tag(key, body, SESSION_MAGIC)):
        return None
    boot, echo_us = _SESSION.unpack_from(body)
    return boot, echo_us, body[_SESSION.size:]


def record_tag(key: bytes, payload: bytes) -> bytes:
    """The keyed tag of a record a node keeps on disk and must know it wrote itself (the driver host's estop latch,
    bridge/nodes/driver_host.py): its own magic, so a datagram's tag is never a record's even under one key."""
    return _tag(key, payload, RECORD_MAGIC)


def record_tag_ok(key: bytes, payload: bytes, tag: bytes) -> bool:
    """Whether ``tag`` is :func:`record_tag` of ``payload`` under ``key`` (compared in constant time)."""
    return hmac.compare_digest(tag, record_tag(key, payload))


def seal(key: bytes, payload: bytes) -> bytes:
    """The datagram carrying ``payload`` with its tag."""
    return MAGIC + _tag(key, payload) + payload


def open_sealed(key: bytes, datagram: bytes) -> bytes | None:
    """The payload if ``datagram`` is sealed with ``key``, else None (forged, corrupted, or unauthenticated)."""
    if len(datagram) < OVERHEAD or datagram[: len(MAGIC)] != MAGIC:
        return None
    tag, payload = datagram[len(MAGIC):OVERHEAD], datagram[OVERHEAD:]
    return payload if hmac.compare_digest(tag, _tag(key, payload)) else None


def key_path(robot: str, link: str) -> Path:
    """Where ``scmbridge keys LINK --robot ROBOT`` keeps the key: ``<state dir>/keys/<robot>-<link>.key``."""
    return state_dir() / "keys" / f"{robot}-{link}.key"


def make_key(path: Path, *, force: bool = False, key: bytes | None = None) -> bytes:
    """Write a new random key (or ``key``, one derived elsewhere: a MAVLink signing passphrase's) to ``path`` (mode
    0600, atomically); refuses to replace a different one unless ``force`` (the same key is written again)."""
    path = Path(path)
    if key is not None and len(key) != KEY_BYTES:
        raise ValueError(f"a key is {KEY_BYTES} bytes")
    if path.exists() and not force:
        try:
            same = key is not None and read_key_file(path) == key
        except (OSError, KeyProblem):
            same = False
        if not same:
            raise KeyFileError(f"{path} exists (both ends use it); give --force to replace it")
    key = secrets.token_bytes(KEY_BYTES) if key is None else key
    old = os.umask(0o077)
    try:
        save_atomic(path, key.hex().encode() + b"\n")
    finally:
        os.umask(old)
    os.chmod(path, 0o600)
    return key


def create_key(path: Path, link: str = "station") -> tuple[bytes, bool]:
    """The key at ``path``, made now if there is none: ``(key, made)``. Of the processes or threads making the same
    key at once, one writes it and the others read what it wrote (:func:`bridge.core.paths.save_new`), so each of
    them tags its files with the key that is on disk (two robots of one station host share their directory's key)."""
    path = Path(path)
    key = secrets.token_bytes(KEY_BYTES)
    old = os.umask(0o077)
    try:
        made = save_new(path, key.hex().encode() + b"\n")
    finally:
        os.umask(old)
    return (key, True) if made else (load_key(path, link), False)


class KeyProblem(ValueError):
    """A key file that exists but is not a usable key: ``kind`` is ``"mode"`` (others may read it) or ``"format"``
    (not :data:`KEY_BYTES` bytes as hex, or not text)."""

    def __init__(self, kind: str, text: str) -> None:
        super().__init__(text)
        self.kind = kind


def read_key_file(path: Path) -> bytes:
    """The key held in ``path`` as hex, under the checks every key file of the project gets (a link's key and the
    estop latch's install marker alike): readable by its owner only, exactly :data:`KEY_BYTES` bytes. Raises
    FileNotFoundError when there is none, OSError when it cannot be read, :class:`KeyProblem` otherwise; the callers
    word the error for their user."""
    try:  # a regular file of a key's size: a FIFO would hang the reader, /dev/zero fill its memory
        data = read_bounded(path, SMALL_FILE)
    except NotAFile as exc:
        raise KeyProblem("format", f"{path}: not a key ({exc})") from None
    st = path.stat()
    try:
        text = data.decode("ascii").strip()
    except UnicodeDecodeError as exc:
        raise KeyProblem("format", f"{path}: not a key ({exc})") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise KeyProblem("mode", f"{path} is readable by others (mode {stat.S_IMODE(st.st_mode):o})")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise KeyProblem("format", f"{path}: not a key ({KEY_BYTES} bytes as hex)")
    if not any(key):  # what a placeholder or a zeroed file holds: anyone can guess it
        raise KeyProblem("format", f"{path}: an all-zero key (not random: anyone can sign with it)")
    return key


def load_key(path: str | Path, link: str = "udp") -> bytes:
    """The key in ``path``; refuses a missing, malformed or group/world-readable file with one line."""
    path = Path(path)
    try:
        return read_key_file(path)
    except FileNotFoundError:
        raise KeyFileError(f"key file {path} not found (make one: scmbridge keys {link} --robot NAME)") from None
    except KeyProblem as exc:
        if exc.kind == "mode":
            mode = stat.S_IMODE(path.stat().st_mode)
            raise KeyFileError(f"key file {path} is readable by others (mode {mode:o}); chmod 600 it") from None
        raise KeyFileError(f"key file {path}: expected {KEY_BYTES} random bytes as hex (scmbridge keys makes one): "
                           f"{exc}") from None
    except OSError as exc:
        raise KeyFileError(f"key file {path}: cannot read it ({exc})") from None


__all__ = ["KEY_BYTES", "MAGIC", "OVERHEAD", "RECORD_MAGIC", "SESSION_MAGIC", "SESSION_OVERHEAD", "KeyFileError",
           "KeyProblem", "create_key", "key_path", "load_key", "make_key", "open_sealed", "open_session",
           "read_key_file", "record_tag", "record_tag_ok", "seal", "seal_session"]
