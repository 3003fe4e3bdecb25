"""Argument types every command shares: a mistake is one argparse line and exit status 2."""

from __future__ import annotations

import argparse
import math

from bridge.core.wire import check_robot


def pose_arg(text: str) -> tuple[float, float, float]:
    """``x,y,theta``: three finite numbers."""
    try:
        vals = tuple(float(a) for a in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not x,y,theta (three numbers)") from None
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"{text!r} is not x,y,theta (three finite numbers)")
    return vals  # type: ignore[return-value]


def positive_float(text: str) -> float:
    """A finite number > 0 (a rate, a duration)."""
    try:
        val = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(val) and val > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return val


def robot_arg(text: str) -> str:
    """A robot name: one Zenoh key chunk (``[A-Za-z0-9_-]``, 1-64 characters)."""
    try:
        return check_robot(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def robots_arg(text: str) -> list[str]:
    """Comma-separated robot names (at least one, no repeats)."""
    names = [robot_arg(a.strip()) for a in text.split(",") if a.strip()]
    if not names:
        raise argparse.ArgumentTypeError("give at least one robot name")
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"{text!r} names a robot twice")
    return names
