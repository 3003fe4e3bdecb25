"""``scmbridge keys udp|mavlink --robot R``: make the secret key a link authenticates with, in the state directory
(``<state>/keys/<robot>-<link>.key``, mode 0600), and print its path. Give the same file to both ends: the driver
host's ``[link.udp] key_file`` (or ``[link.mavlink] signing_key_file``) and the robot (the UDP shim's firmware, or
the autopilot through MAVLink 2 signing set-up). ``--out FILE`` writes it elsewhere; an existing key is kept unless
``--force`` (every robot using it would stop answering).

MAVLink signing as ground stations set it up: ``keys mavlink --passphrase PASSPHRASE`` writes the key MAVProxy's
``signing setup PASSPHRASE`` (and Mission Planner's signing page) makes of the same passphrase, its SHA-256, so the
driver host, the ground station and the autopilot share it (``--passphrase -`` reads it from the first line of
standard input, out of the shell's history). ``--install --driver FILE`` then sends it to the vehicle over the link
that driver configuration names (SETUP_SIGNING: a person's explicit act; the vehicle's mode, arming and parameters
are not touched) and confirms that a request signed with the key is answered and an unsigned one is refused; exit
status 1 when either is not so (ArduPilot takes unsigned messages on its USB port whatever the key: check over the
radio's port). ``--old-key FILE``: the key the vehicle holds now, when it is signed already (it takes a new key only
signed with the old one, but on its USB port). Stop the driver host first: a serial port opens once.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bridge.core.args import positive_float, robot_arg
from bridge.core.auth import key_path, load_key, make_key
from bridge.core.errors import UsageError


def _arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--robot", type=robot_arg, required=True, help="the robot the key is for")
    ap.add_argument("--out", default=None, help="write the key here instead of the state directory")
    ap.add_argument("--force", action="store_true", help="replace an existing key")


def _run(args: argparse.Namespace, link: str, key: bytes | None = None) -> Path:
    path = Path(args.out) if args.out else key_path(args.robot, link)
    make_key(path, force=args.force, key=key)
    print(path)
    return path


def arguments_udp(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)


def run_udp(args: argparse.Namespace) -> int:
    """Make the UDP shim's datagram key (every datagram carries a keyed BLAKE2b tag)."""
    _run(args, "udp")
    return 0


def arguments_mavlink(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)
    ap.add_argument("--passphrase", default=None,
                    help="the key is this passphrase's SHA-256, as MAVProxy's `signing setup PASSPHRASE` makes it "
                         "(ASCII; '-': read it from standard input)")
    ap.add_argument("--install", action="store_true",
                    help="send the key to the vehicle (SETUP_SIGNING) over the link --driver names, and confirm "
                         "signed requests answered and unsigned ones refused")
    ap.add_argument("--driver", default=None, help="with --install: the driver host's configuration ([link.mavlink])")
    ap.add_argument("--old-key", default=None, help="with --install: the key the vehicle holds now, if any")
    ap.add_argument("--timeout", type=positive_float, default=None,
                    help="with --install: s for the vehicle to answer (default: [link.mavlink] open_timeout)")


def run_mavlink(args: argparse.Namespace) -> int:
    """Make the MAVLink 2 signing key (the secret both the driver host and the autopilot sign with); from a
    passphrase as ground stations do, and install it in the vehicle."""
    from drivers.mavlink.signing import passphrase_key

    key = None
    if args.passphrase is not None:
        phrase = sys.stdin.readline().rstrip("\r\n") if args.passphrase == "-" else args.passphrase
        try:
            key = passphrase_key(phrase)
        except ValueError as exc:
            raise UsageError(f"--passphrase: {exc}") from None
    if args.install and args.driver is None:
        raise UsageError("--install needs --driver FILE (the link to the vehicle: [link.mavlink])")
    path = _run(args, "mavlink", key)
    if not args.install:
        return 0
    from bridge.nodes.driver_config import load_driver
    from drivers.mavlink.signing import install

    cfg = load_driver(args.driver).link.mavlink
    old = load_key(args.old_key, "mavlink") if args.old_key else None
    try:
        res = install(cfg, load_key(path, "mavlink"), old_key=old, timeout=args.timeout)
    except OSError as exc:
        raise UsageError(f"cannot open {cfg.url}: {exc} (is the driver host running on it?)") from None
    for line in res.lines:
        print(line)
    if res.ok:
        print(f"signing on: name {path} in [link.mavlink] signing_key_file")
    return 0 if res.ok else 1
