"""Small argument types the commands share: a user's mistake is one argparse line and exit status 2."""

from __future__ import annotations

import argparse
import math


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
