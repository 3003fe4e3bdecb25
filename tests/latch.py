"""What the tests of the estop latch on disk share (bridge/nodes/latch_store.py on its own, and the driver host that
keeps one: tests/unit/bridge/nodes/test_latch_store.py, tests/integration/test_driver_host.py): a disk that fills on
cue, and a wait on the latch writer's own confirmation (no sleep)."""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

from bridge.core.paths import save_atomic
from bridge.nodes.latch_store import LatchStore


class FullDisk:
    """A latch saver (``LatchStore``'s and ``DriverHost``'s ``latch_saver``) that saves as the real one does
    (:func:`bridge.core.paths.save_atomic`) and fails with ``error`` (default ENOSPC: a full disk) while ``full`` is
    set; ``saves`` lists the paths it wrote. Injected, because the suite runs as root, which a read-only chmod does
    not stop, and a tmpfs of its own needs privileges the suite does not assume."""

    def __init__(self, error: int = errno.ENOSPC) -> None:
        self.error = error
        self.full = threading.Event()
        self.saves: list[Path] = []

    def __call__(self, path: Path, data: bytes) -> None:
        if self.full.is_set():
            raise OSError(self.error, os.strerror(self.error), str(path))
        save_atomic(path, data)
        self.saves.append(path)


def wait_saved(store: LatchStore) -> None:
    """Wait until every latch handed to ``store``'s writer has been saved (or its save failed), at most 10 s."""
    done = threading.Event()
    if store.defer(done.set):
        assert done.wait(10.0), "the latch save never finished"
