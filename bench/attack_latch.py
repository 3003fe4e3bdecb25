"""``scmbridge bench attack`` rows on the estop latch on disk (docs/SECURITY.md's attack table): a latch that cannot
be saved, deleted, forged "released" files and another state directory, each against a real DriverHost on a real
state directory with the emulated UDP robot; each row's docstring gives its "before".
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from bench.attack_rigs import (
    Result,
    _LatchRig,
)


def latch_disk_full_at_estop(short: bool) -> Result:
    """The robot's disk is full when the operator's estop comes (the latch save fails with ENOSPC, injected as the
    host's saver: the bench runs as root, which a read-only directory does not stop), then the host restarts on the
    same state directory and someone engages. bridge/nodes/latch_store.py: the failed save removes the old
    (released) file and the host refuses engage, so the restart finds the marker without a file: latched. before
    (the save result's handling off: the failure ignored, the old released file left; --short, two runs): engaged
    after the restart, drove 0.073 m in 0.5 s both times."""
    import errno
    import os
    import threading

    from bridge.core.paths import save_atomic

    full = threading.Event()

    def saver(path: Path, data: bytes) -> None:
        if full.is_set():
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        save_atomic(path, data)

    with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
        latch = Path(d) / "state" / "estop-r1.bin"
        host = rig.host(latch, saver)
        full.set()
        rig.estop(host)
        refused_before_restart = not rig.engage_and_drive(host, 0.1)["engaged"]
        rig.stop(host)
        host = rig.host(latch, saver)
        after = rig.engage_and_drive(host, 0.5 if short else 1.5)
        full.clear()  # space freed: a person's release is saved, and the host drives again
        control = rig.control(host, 0.3)
    return {"reached_vehicle": after, "learned": None, "engage_refused_before_restart": refused_before_restart,
            "control_drove_m": control,
            "ok": not after["engaged"] and after["distance_m"] < 0.01 and refused_before_restart and control > 0.01}


def latch_file_deleted(short: bool) -> Result:
    """The operator latched the estop; while the host was stopped the latch file was deleted; the host restarts and
    someone engages. The install marker beside it says this directory has an estop history: a missing file is
    latched. before (``inspect_latch`` as a plain read: missing means never latched; --short, two runs): engaged,
    drove 0.092 and 0.073 m in 0.5 s."""
    with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
        latch = Path(d) / "estop-r1.bin"
        host = rig.host(latch)
        rig.estop(host)
        rig.stop(host)
        latch.unlink()
        host = rig.host(latch)
        after = rig.engage_and_drive(host, 0.5 if short else 1.5)
        control = rig.control(host, 0.3)
    return {"reached_vehicle": after, "learned": None, "control_drove_m": control,
            "ok": not after["engaged"] and after["distance_m"] < 0.01 and control > 0.01}


def forged_releases(other: Path) -> list[bytes]:
    """"Released" latch files someone else wrote: unsigned, with a made-up tag, the one another state directory's
    host signed (``other``), and one signed with another key (also tests/integration/test_driver_host.py)."""
    import os

    from bridge.core import wire as M
    from bridge.nodes.latch_store import Latch, sign_latch

    return [M.encode(Latch(latched=False, source="operator")),
            M.encode(Latch(latched=False, source="operator", tag=os.urandom(16))),
            other.read_bytes(),
            M.encode(sign_latch(os.urandom(32), Latch(latched=False, source="operator")))]


def latch_file_forged_release(short: bool) -> Result:
    """The operator latched the estop; while the host was stopped the latch file was replaced by a "released" one
    this host did not sign (unsigned, a made-up tag, another state directory's host's own signed release, signed
    with a random key); after each, the host restarts and someone engages. Only a release under the robot's latch
    key (its install marker, 0600) is believed. before (``inspect_latch`` as a plain read: any file saying released
    believed; --short, two runs): engaged on 4 of 4, drove 0.061 and 0.048 m in all (0.15 s each)."""
    engaged, moved = 0, 0.0
    with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
        latch, other = Path(d) / "a" / "estop-r1.bin", Path(d) / "b" / "estop-r1.bin"
        rig.stop(rig.host(other))  # another state directory's host: its own key, a released file it signed
        host = rig.host(latch)
        rig.estop(host)
        rig.stop(host)
        forged = forged_releases(other)
        for data in forged:
            latch.write_bytes(data)
            host = rig.host(latch)
            after = rig.engage_and_drive(host, 0.15 if short else 0.5)
            engaged += after["engaged"]
            moved += after["distance_m"]
            rig.stop(host)
        control = rig.control(rig.host(latch), 0.8)  # (a new host: the robot follows its epoch 0.3 s after the last)
    return {"reached_vehicle": {"engaged": engaged, "of": len(forged), "distance_m": round(moved, 3)},
            "learned": None, "control_drove_m": control, "ok": engaged == 0 and moved < 0.01 and control > 0.01}


def latch_other_state_dir(short: bool) -> Result:
    """The operator latched the estop; the host restarts with another (empty) state directory (a changed
    SCMBRIDGE_STATE_DIR). It cannot know of the estop latched in the first one; what it must do is say so, at start:
    "first start in this state directory: no estop history" (log, and ``scmbridge doctor``), once. before
    (791b027's DriverHost, the same two directories): released, and nothing logged."""
    import logging

    class _Said(logging.Handler):
        def __init__(self) -> None:
            super().__init__(logging.INFO)
            self.texts: list[str] = []

        def emit(self, record: logging.LogRecord) -> None:
            self.texts.append(record.getMessage())

    said = _Said()
    logger = logging.getLogger("scmbridge.driver")
    level = logger.level
    logger.addHandler(said)
    logger.setLevel(logging.INFO)
    try:
        with tempfile.TemporaryDirectory() as d, _LatchRig() as rig:
            first = rig.host(Path(d) / "one" / "estop-r1.bin")
            rig.estop(first)
            rig.stop(first)
            said.texts.clear()
            other = rig.host(Path(d) / "two" / "estop-r1.bin")
            told = any("first start in this state directory: no estop history" in t for t in said.texts)
            fresh = other.latch.fresh_state
            rig.stop(other)
    finally:
        logger.removeHandler(said)
        logger.setLevel(level)
    return {"reached_vehicle": None, "learned": None, "said_no_estop_history": told, "fresh_state": fresh,
            "ok": told and fresh}
