"""Shared helpers for the benchmarks: timing summaries in one consistent JSON form."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable

import numpy as np


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
    json.dump(result, sys.stdout, indent=2, sort_keys=False)
    sys.stdout.write("\n")
    sys.stdout.flush()
