"""MAVLink 2 signing as ArduPilot does it, for the emulated rover (:mod:`sim_learner.mavlink_rover`).

From libraries/GCS_MAVLink/GCS_Signing.cpp, as SETUP_SIGNING leaves it: with ``signing_key``, every message
it sends is signed, and a message that is unsigned (other than RADIO_STATUS / RADIO), badly signed or whose
signature timestamp goes back on its stream is refused before it is handled (counted in ``bad_signatures``). The
check runs in the C library's order (generated mavlink_helpers.h ``mavlink_signature_check``): the signature
first, then the stream's timestamp (a new stream is taken if at most one minute behind ours), and only a verified
message records its stream's timestamp and raises ours; pymavlink's own check records it first, so one forged
packet could lock the ground station out (docs/SECURITY.md). One signing state serves sending and receiving, as
``mavlink_signing_t`` does on every channel. The timestamp survives a reboot as ArduPilot keeps it:
``signing_store`` stands for the autopilot's storage (StorageKeys); the timestamp is saved when a HEARTBEAT is
queued if ``signing_save_s`` (30 s, ``save_signing_timestamp(false)``) have passed since the last save, and at once
when the GPS gives the time (``update_signing_timestamp``, below: the timestamp rises to the GPS's UTC and
``save_signing_timestamp(true)``), and only if it grew. At boot
(``load_signing_key``) the timestamp is the stored one plus one minute. ArduPilot saves nothing at power-off, so a
message signed after the last save is still taken after a reboot (as a new stream: at most one minute behind);
everything signed before the last save is refused. Without a store (or none saved yet, or one saved for another
key: the store keeps a digest of the key beside the timestamp) the key counts as just set by SETUP_SIGNING from a
ground station, whose ``initial_timestamp`` is its wall clock; it is saved then.

The GPS's time (libraries/AP_RTC/AP_RTC.cpp ``set_utc_usec``, which calls ``update_signing_timestamp``): the first
time the GPS gives is always taken; later ones only while the vehicle is disarmed (the same source may not move the
clock while armed) and only forward. Each one raises the timestamp to the GPS's UTC (here the wall clock, at the
GPS's rate ``GPS_PERIOD`` once the EKF has its origin) and saves it at once. So while disarmed the stored timestamp
is never more than a GPS period behind the time, and a recording of anything signed before the vehicle was last
disarmed is refused after a reboot; what was signed while it stayed armed after the last save (at most
``signing_save_s`` of traffic) is taken by a rebooted vehicle as a new stream while it is less than a minute old.
docs/SECURITY.md gives what SITL (the firmware itself) measured.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bridge.core.paths import save_atomic
from sim_learner.mavlink_dialect import MAV

#: GCS_Signing.cpp: the timestamp is saved every 30 s (when a HEARTBEAT is queued), and at boot it starts one
#: minute past the saved one; both in 10 us units since 2015-01-01 where a timestamp is meant
SIGNING_SAVE_S = 30.0
SIGNING_BOOT_AHEAD = 60 * 100 * 1000
#: a new signing stream is taken if its timestamp is at most this far behind ours (mavlink_signature_check)
SIGNING_NEW_STREAM = 6000 * 1000
_EPOCH_2015 = 1420070400


def signing_wall_clock() -> int:
    """Now in MAVLink signing units (10 us since 2015-01-01 UTC), as a GPS or a ground station gives it."""
    return int(max(0.0, time.time() - _EPOCH_2015) * 100_000)


def c_order_check(mav: Any) -> Callable[[bytearray, int, int], bool]:
    """``mavlink_signature_check`` of the C library for ``mav``: the signature first, then the timestamp against the
    stream's last one (or, for a new stream, against ours less one minute); only then are both recorded."""
    unpack = struct.Struct("<IH").unpack

    def check(msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        sig = mav.signing
        if hashlib.sha256(bytes(sig.secret_key) + bytes(msgbuf[:-6])).digest()[:6] != bytes(msgbuf[-6:]):
            return False
        low, high = unpack(bytes(msgbuf[-12:-6]))
        stamp = low + (high << 32)
        stream = (msgbuf[-13], src_system, src_component)
        last = sig.stream_timestamps.get(stream)
        if (last is None and stamp + SIGNING_NEW_STREAM < sig.timestamp) or (last is not None and stamp <= last):
            return False
        sig.stream_timestamps[stream] = stamp
        sig.timestamp = max(sig.timestamp, stamp)
        return True

    return check


def accept_unsigned(mav: Any, msg_id: int) -> bool:
    """GCS_Signing.cpp ``accept_unsigned_callback``: a radio's own status messages pass unsigned, nothing else."""
    return msg_id in (MAV.MAVLINK_MSG_ID_RADIO_STATUS, MAV.MAVLINK_MSG_ID_RADIO)


#: how often the GPS gives the time (a GPS's 5 Hz)
GPS_PERIOD = 0.2


class SigningMixin:
    """The rover's signing state: its key, the stored timestamp, the GPS's time (see the module docstring)."""

    mav: Any
    _parser: Any
    armed: bool

    def has_origin(self, now: float) -> bool:
        raise NotImplementedError

    def _init_signing(self, signing_key: bytes | None, signing_store: str | os.PathLike[str] | None,
                      signing_save_s: float) -> None:
        self.signing_store = Path(signing_store) if signing_store is not None else None
        self.signing_save_s = float(signing_save_s)
        self.signing_saves = 0  # timestamps written to the store
        self._signing_saved = 0  # the timestamp in the store
        self._signing_save_time = -math.inf
        self._gps_time = False  # the GPS has given the time (update_signing_timestamp done)
        if signing_key is not None:  # GCS_Signing.cpp: once a key is set, unsigned messages are refused
            sig = self.mav.signing
            self._parser.signing = sig  # one mavlink_signing_t for both directions
            sig.secret_key = signing_key
            sig.sign_outgoing = True
            sig.link_id = 0
            sig.allow_unsigned_callback = accept_unsigned
            stored = self._load_signing_timestamp()
            if stored is None:  # SETUP_SIGNING from a ground station: its clock, saved (handle_setup_signing)
                sig.timestamp = signing_wall_clock()
                self._save_signing_timestamp(time.monotonic(), force=True)
            else:  # load_signing_key: one minute past the last recorded
                self._signing_saved = stored
                sig.timestamp = stored + SIGNING_BOOT_AHEAD
            self._parser.check_signature = c_order_check(self._parser)
        self._gps_next = -math.inf  # the GPS's next time

    def _gps_update(self, now: float) -> None:
        """The GPS gives the time (``AP_RTC::set_utc_usec``): the first time always, later ones while disarmed;
        the timestamp rises to it and is saved at once (``update_signing_timestamp``)."""
        if self.mav.signing.secret_key is None or now < self._gps_next or not self.has_origin(now):
            return
        self._gps_next = now + GPS_PERIOD
        if self._gps_time and self.armed:
            return
        self._gps_time = True
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, signing_wall_clock())
        self._save_signing_timestamp(now, force=True)

    def _gps_due(self) -> float:
        """When :meth:`_gps_update` has something to do next (the scheduler's event)."""
        return self._gps_next if self.mav.signing.secret_key is not None else math.inf

    def _load_signing_timestamp(self) -> int | None:
        """The timestamp in the store (None: no store, nothing saved yet, or unreadable)."""
        if self.signing_store is None:
            return None
        try:
            saved = json.loads(self.signing_store.read_text(encoding="utf-8"))
            value, key = saved["timestamp"], saved["key"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if key != self._key_id():  # another key: SETUP_SIGNING replaced the stored key and its timestamp
            return None
        return int(value) if isinstance(value, int) and value > 0 else None

    def _key_id(self) -> str:
        """What the store keeps of the key (ArduPilot keeps the key itself; a file here keeps a digest)."""
        return hashlib.blake2b(bytes(self.mav.signing.secret_key or b""), digest_size=8).hexdigest()

    def _save_signing_timestamp(self, now: float, force: bool = False) -> None:
        """``save_signing_timestamp``: every ``signing_save_s`` unless forced, and only a timestamp that grew."""
        if self.mav.signing.secret_key is None or (not force and now - self._signing_save_time < self.signing_save_s):
            return
        self._signing_save_time = now
        stamp = int(self.mav.signing.timestamp)
        if stamp <= self._signing_saved:
            return
        self._signing_saved = stamp
        if self.signing_store is not None:
            save_atomic(self.signing_store, json.dumps({"key": self._key_id(), "timestamp": stamp}).encode())
        self.signing_saves += 1

    @property
    def signing_timestamp(self) -> int:
        """The vehicle's signing timestamp now (10 us units since 2015)."""
        return int(self.mav.signing.timestamp)


__all__ = ["GPS_PERIOD", "SIGNING_BOOT_AHEAD", "SIGNING_NEW_STREAM", "SIGNING_SAVE_S", "SigningMixin",
           "accept_unsigned", "c_order_check", "signing_wall_clock"]
