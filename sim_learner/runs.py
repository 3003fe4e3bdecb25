"""What the paper's simulations share: the control interval and a progress line (``sim mpc``, ``sim primitives``)."""

from __future__ import annotations

import sys

DT = 0.1  # s, the paper's control interval


class Progress:
    """A one-line progress bar on stderr when it is a terminal; silent otherwise."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.tty = sys.stderr.isatty()

    def __call__(self, frac: float, text: str = "") -> None:
        if self.tty:
            n = int(30 * min(max(frac, 0.0), 1.0))
            sys.stderr.write(f"\r{self.label:>10} [{'#' * n}{'.' * (30 - n)}] {100 * frac:5.1f}% {text:<30}")
            sys.stderr.flush()

    def done(self) -> None:
        if self.tty:
            sys.stderr.write("\n")
