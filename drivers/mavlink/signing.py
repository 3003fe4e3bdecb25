"""MAVLink 2 signing set up as ground stations do it: a key from a passphrase, sent to the vehicle with SETUP_SIGNING,
and the result checked on the link itself.

The key of a passphrase is its SHA-256 (MAVProxy's ``signing setup PASSPHRASE``, modules/mavproxy_signing.py
``passphrase_to_key``, which takes ASCII passphrases only; Mission Planner's signing page hashes its passphrase the
same way), so the driver host, MAVProxy and the autopilot hold the same 32 bytes from one passphrase.

:func:`install` is a person's explicit act (``scmbridge keys mavlink --install``): it never changes the vehicle's mode,
arming or parameters; SETUP_SIGNING stores the key in the autopilot (ArduPilot libraries/GCS_MAVLink/GCS_Signing.cpp
``handle_setup_signing``), which from then on signs what it sends and refuses unsigned messages on every port but its
USB one (SERIAL0). The confirmation asks the vehicle for a message (MAV_CMD_REQUEST_MESSAGE AUTOPILOT_VERSION, a read)
signed, which must be acknowledged, then unsigned, which must not be. docs/SECURITY.md and docs/OPERATING.md ("First
day with your rover") say where it fits.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

from bridge.core import timebase
from drivers.mavlink.client import verify_before_recording
from drivers.mavlink.config import MavlinkLinkConfig
from drivers.mavlink.probe import Probe

#: MAVLink signing timestamps count 10 us units from 2015-01-01 00:00:00 UTC
SIGNING_EPOCH = 1420070400
#: s an unsigned request goes unanswered before it counts as refused (three tries a second)
UNSIGNED_WAIT_S = 2.0


def passphrase_key(passphrase: str) -> bytes:
    """The 32-byte signing key of ``passphrase``: its SHA-256, as MAVProxy's ``signing setup`` makes it. A passphrase
    MAVProxy could not take (empty, not ASCII, or more than one word: ``signing setup`` hashes its first word only)
    is refused with ValueError."""
    if not passphrase:
        raise ValueError("an empty passphrase")
    if any(c.isspace() for c in passphrase):
        raise ValueError("the passphrase has white space (MAVProxy's signing setup would take its first word only)")
    try:
        raw = passphrase.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError("the passphrase is not ASCII (MAVProxy's signing setup takes ASCII only)") from None
    return hashlib.sha256(raw).digest()


def signing_timestamp(now: float | None = None) -> int:
    """Now as a MAVLink 2 signing timestamp (10 us units since 2015-01-01 UTC)."""
    return int((max(timebase.wall() if now is None else now, SIGNING_EPOCH) - SIGNING_EPOCH) * 100_000)


@dataclass
class InstallResult:
    """What :func:`install` saw: whether the vehicle answered, took the key (a signed request acknowledged, its own
    messages signed with the key) and refuses unsigned requests; ``lines`` say it in words."""

    heard: bool = False
    signed_accepted: bool = False
    vehicle_signs: bool = False
    unsigned_refused: bool = False
    lines: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.heard and self.signed_accepted and self.vehicle_signs and self.unsigned_refused


def install(config: MavlinkLinkConfig, key: bytes, *, old_key: bytes | None = None,
            timeout: float | None = None) -> InstallResult:
    """Send SETUP_SIGNING with ``key`` to the vehicle ``config`` names, over its link, and confirm it: a signed
    request acknowledged, the vehicle's HEARTBEATs signed with the key, an unsigned request refused. ``old_key``: the
    key the vehicle holds now (a signed vehicle takes a new key only signed with the old one, but on its USB port).
    Bounded by ``timeout`` (``config.open_timeout`` by default) for the vehicle to answer."""
    if len(key) != 32:
        raise ValueError("a MAVLink 2 signing key is 32 bytes")
    res = InstallResult()
    wait = config.open_timeout if timeout is None else timeout
    link = Probe(config)
    try:
        mav = link.d.mav
        if old_key is not None:
            link.conn.setup_signing(old_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: True)
        if not link.wait(lambda: link.heartbeats > 0, wait):
            res.lines.append(f"FAIL no HEARTBEAT from system {config.target_system} component "
                             f"{config.target_component} on {config.url} within {wait:g} s")
            return res
        res.heard = True
        link.conn.mav.setup_signing_send(*link.target, list(key), signing_timestamp())
        res.lines.append(f"sent SETUP_SIGNING to system {config.target_system} component "
                         f"{config.target_component} on {config.url}")
        link.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=None)
        verify_before_recording(link.conn.mav)
        version = mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION
        result = link.request(version, min(wait, 5.0))
        res.signed_accepted = result == mav.MAV_RESULT_ACCEPTED
        res.lines.append(("ok   " if res.signed_accepted else "FAIL ") + "a request signed with the key: " + (
            "no answer" if result is None else mav.enums["MAV_RESULT"][result].name))
        n = link.signed_from_vehicle
        res.vehicle_signs = link.wait(lambda: link.signed_from_vehicle > n, 3.0)
        res.lines.append("ok   the vehicle's HEARTBEATs come signed with the key" if res.vehicle_signs else
                          "FAIL no HEARTBEAT signed with the key within 3 s (the vehicle did not take it?)")
        link.conn.mav.signing.sign_outgoing = False
        result = link.request(version, UNSIGNED_WAIT_S)
        link.conn.mav.signing.sign_outgoing = True
        res.unsigned_refused = result is None
        res.lines.append("ok   an unsigned request: refused (no answer)" if res.unsigned_refused else
                         "FAIL an unsigned request was answered: this port still takes unsigned messages (ArduPilot "
                         "does on its USB port, SERIAL0, whatever the key): check over the radio's port")
        return res
    finally:
        link.close()
