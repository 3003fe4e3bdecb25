"""``scmbridge replay``: the command's entry point; the replay itself lives in :mod:`bridge.tools.record`, next to the
recording format it reads (``scmbridge`` runs ``main`` of one module per command)."""

from __future__ import annotations

from bridge.tools.record import replay_main


def main(argv: list[str] | None = None) -> int:
    return replay_main(argv)
