"""Shared helpers for the benchmarks: timing summaries in one consistent JSON form, the emulated CAN rig."""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from contextlib import ExitStack
from typing import Any

import numpy as np

from bridge.core.logsink import print_line


def summary_us(samples_s: Iterable[float], pcts: tuple[int, ...] = (95,)) -> dict[str, float]:
    """``{"median": ..., "p95": ...}`` in microseconds from samples in seconds."""
    a = np.asarray(list(samples_s), dtype=float) * 1e6
    if a.size == 0:
        return {"median": float("nan"), **{f"p{p}": float("nan") for p in pcts}, "n": 0}
    out = {"median": float(np.median(a))}
    for p in pcts:
        out[f"p{p}"] = float(np.percentile(a, p))
    out["n"] = int(a.size)
    return out


def emit(result: dict) -> None:
    """Print the benchmark's single JSON object to stdout."""
    print_line(json.dumps(result, indent=2, sort_keys=False))  # one write: no log line lands inside it


def can_ecus(stack: ExitStack, channel: str, vehicle: Any, **ecu_kw: Any) -> Any:
    """The emulated ODrive controllers of ``vehicle`` on the python-can ``virtual`` ``channel``, stopped with
    ``stack``."""
    from sim_learner.can_ecu import DiffDriveEcus

    ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, **ecu_kw).start()
    stack.callback(ecus.stop)
    return ecus


def open_can_driver(stack: ExitStack, channel: str) -> Any:
    """The CAN driver on the ``virtual`` ``channel``, opened (both axes armed), closed with ``stack``."""
    from drivers import open_driver
    from drivers.can import CanLinkConfig

    driver = open_driver("can", CanLinkConfig(interface="virtual", channel=channel))
    stack.callback(driver.close)
    driver.open(time.monotonic())
    driver.engage(time.monotonic(), clear_faults=True)  # a person who has looked at the robot: clear and arm
    return driver
