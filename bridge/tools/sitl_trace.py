"""Where a SITL run's deviation came from (``scmbridge demo --sitl``): its trace written beside its summary
(``trace.json``: each pose with its progress along the path and its distance to it, each applied echo with the
method of the command it applied) and the last half's deviation split by where the vehicle was (a bend of the path
or a straight) and by the method of the command it was driving (docs/BENCHMARKS.md, "A family of vehicles": the
claims are judged on the last half's mean deviation, :mod:`bridge.tools.sitl_verdict`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

#: a point of the path whose heading turns faster than this is on a bend, rad/m (the paper's S-path bends at
#: up to 0.73 rad/m, its straights at 0)
BEND_RAD_PER_M = 0.2


def curvature_at(path: Any, s: float, ds: float = 0.05) -> float:
    """The path's curvature at arc length ``s`` (rad/m, unsigned): its heading's change over ``2 ds`` around it."""
    a, b = path.at(np.array([max(0.0, s - ds), min(path.length, s + ds)]))
    span = min(path.length, s + ds) - max(0.0, s - ds)
    turn = (float(b[2]) - float(a[2]) + np.pi) % (2 * np.pi) - np.pi
    return abs(turn) / span if span > 0 else 0.0


def write_trace(path: Path, states: list, applied: list, cmds: dict[int, str], world: Any) -> dict[str, Any]:
    """Write and return the run's trace: ``poses`` rows (driver host's stamp, x, y, theta, progress 0-1, distance
    to the path, m, the path's curvature at the nearest point, rad/m) and ``applied`` rows (stamp, reason, the
    method of the command applied or None)."""
    rows = []
    for t, x, y, th in states:
        s_arc, d = world.path.project(np.array([x, y]))
        rows.append([round(t, 3), round(x, 4), round(y, 4), round(th, 4), round(s_arc / world.path.length, 4),
                     round(float(d), 4), round(curvature_at(world.path, s_arc), 3)])
    echoes = [[round(t, 3), reason, cmds.get(seq) if seq is not None else None] for t, reason, seq in applied]
    trace = {"poses": rows, "applied": echoes}
    path.write_text(json.dumps(trace))
    return trace


def deviation_sources(trace: dict[str, Any], t0: float, t1: float) -> dict[str, Any]:
    """The last half's deviation (poses between ``t0`` and ``t1`` at progress >= 0.5) split: ``bend`` and
    ``straight`` (by :data:`BEND_RAD_PER_M`) and ``by_method`` (the method of the last command applied at or before
    the pose), each ``{"poses", "share", "mean_dev_m"}``; ``share`` is that part's share of the poses, so
    ``sum(share * mean_dev_m)`` is the last half's mean deviation. Empty parts are left out."""
    poses = [p for p in trace["poses"] if t0 <= p[0] <= t1 and p[4] >= 0.5]
    applied = sorted((a for a in trace["applied"] if a[1] in ("cmd", "clamped")), key=lambda a: a[0])
    stamps = [a[0] for a in applied]

    def part(rows: list) -> dict[str, Any]:
        return {"poses": len(rows), "share": round(len(rows) / len(poses), 3),
                "mean_dev_m": round(float(np.mean([r[5] for r in rows])), 4)}

    out: dict[str, Any] = {"poses": len(poses)}
    if not poses:
        return out
    out["mean_dev_m"] = round(float(np.mean([p[5] for p in poses])), 4)
    for name, rows in (("bend", [p for p in poses if p[6] > BEND_RAD_PER_M]),
                       ("straight", [p for p in poses if p[6] <= BEND_RAD_PER_M])):
        if rows:
            out[name] = part(rows)
    methods: dict[str, list] = {}
    for p in poses:
        i = int(np.searchsorted(stamps, p[0], side="right")) - 1
        methods.setdefault(str(applied[i][2]) if i >= 0 else "none", []).append(p)
    out["by_method"] = {m: part(rows) for m, rows in sorted(methods.items())}
    return out
