"""``scmbridge keys udp|mavlink --robot R``: make the secret key a link authenticates with, in the state directory
(``<state>/keys/<robot>-<link>.key``, mode 0600), and print its path. Give the same file to both ends: the driver
host's ``[link.udp] key_file`` (or ``[link.mavlink] signing_key_file``) and the robot (the UDP shim's firmware, or
the autopilot through MAVLink 2 signing set-up). ``--out FILE`` writes it elsewhere; an existing key is kept unless
``--force`` (every robot using it would stop answering)."""

from __future__ import annotations

import argparse
from pathlib import Path

from bridge.core.args import robot_arg
from bridge.core.auth import key_path, make_key


def _arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--robot", type=robot_arg, required=True, help="the robot the key is for")
    ap.add_argument("--out", default=None, help="write the key here instead of the state directory")
    ap.add_argument("--force", action="store_true", help="replace an existing key")


def _run(args: argparse.Namespace, link: str) -> int:
    path = Path(args.out) if args.out else key_path(args.robot, link)
    make_key(path, force=args.force)
    print(path)
    return 0


def arguments_udp(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)


def run_udp(args: argparse.Namespace) -> int:
    """Make the UDP shim's datagram key (every datagram carries a keyed BLAKE2b tag)."""
    return _run(args, "udp")


def arguments_mavlink(ap: argparse.ArgumentParser) -> None:
    _arguments(ap)


def run_mavlink(args: argparse.Namespace) -> int:
    """Make the MAVLink 2 signing key (the secret both the driver host and the autopilot sign with)."""
    return _run(args, "mavlink")
