"""``scmbridge bench sitl``: the transfer on a family of ArduPilot Rover profiles nobody tuned it for (JSON, table).

For each profile of ``--profiles`` (:mod:`sim_learner.sitl_profiles`: ``dev``, ``heldout``, ``all``, ``N`` or
``N..M`` of the ``--frame``'s family) one ``scmbridge demo --sitl`` run as a person makes it, with ``--baseline``
and the automatic reference: the transfer from no pairs, then the paper's baseline, then the teacher on the stock
rover given the range the transfer learned; each on a freshly booted SITL (:mod:`bridge.tools.demo_sitl_run`). A
profile *meets the goal* when every verdict of its run holds (:mod:`bridge.tools.sitl_verdict`: the goal reached
without collision, never out of the corridor, at most 1.5x the reference's time and last-half deviation, and at
most 0.5x the baseline's deviation, or the baseline collided or missed its goal). A profile whose mission the
station stopped as outside the method's assumption (a car measured to turn less than the path bends:
:mod:`transfer.feasibility`) does not meet the goal, and is counted in its own column: the rate is given strict
(over every profile) and over the profiles inside the assumption.

Printed: a table (stderr) and one JSON object (stdout): each profile's figures and verdicts, and the share of the
profiles that met the goal. SITL runs in real time: ``--jobs`` (at most 2) profiles at once; a loaded machine
slows the station and SITL alike (docs/BENCHMARKS.md says the load of each figure there).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from bench.common import emit

#: what each row shows of a run's summary
COLUMNS = ("learner_reached_goal", "learner_time_ratio", "learner_dev_ratio", "learner_max_dev_m",
           "baseline_reached_goal", "baseline_collided")


#: what each row keeps of a run's summary besides (the table in docs/BENCHMARKS.md is made from them)
FIGURES = ("learner_dev_last_half_m", "baseline_dev_last_half_m", "reference_dev_last_half_m", "baseline_dev_ratio",
           "learner_time_s", "reference_time_s", "learner_bounds", "vehicle_params")


def demo_command(profile: Any, binary: str, parm: Path, out: Path, duration: float, mission: str | None,
                 identify: bool = True) -> list[str]:
    """The demo as a person runs it on this profile: the transfer, then the baseline, then the reference."""
    return [sys.executable, "-m", "bridge", "demo", "--link", "mavlink", "--sitl", binary, "--sitl-model",
            profile.model, "--sitl-params", str(parm), "--baseline", "--duration", str(duration), "--out", str(out),
            *(["--mission", mission] if mission else []), *([] if identify else ["--no-identify"])]


def run_profile(profile: Any, binary: str, out: Path, duration: float, mission: str | None,
                identify: bool = True) -> dict[str, Any]:
    """One profile: its parameter file written, the demo run to its end (bounded), its summary read back."""
    out.mkdir(parents=True, exist_ok=True)
    parm = out / f"{profile.name}.parm"
    parm.write_text(profile.parm())
    cmd = demo_command(profile, binary, parm, out / "run", duration, mission, identify)
    t0 = time.monotonic()
    with open(out / "demo.log", "w") as log:
        try:
            rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, timeout=3 * (duration + 240)).returncode
        except subprocess.TimeoutExpired:
            rc = None
    row = {"profile": profile.name, "split": profile.split, "params": profile.params, "rc": rc,
           "wall_s": round(time.monotonic() - t0, 1), "log": str(out / "demo.log")}
    return {**row, **judge((out / "demo.log").read_text())}


def judge(log: str) -> dict[str, Any]:
    """A profile's figures and whether it met the goal, from the demo's output ``log`` (its last ``summary:``
    line): met only if every claim was judged and held."""
    lines = [ln for ln in log.splitlines() if ln.startswith("summary: ")]
    if not lines:
        return {"worked": False, "why": "no summary (see the log)"}
    s = json.loads(lines[-1][len("summary: "):])
    failed = [k for k, ok in s.get("verdicts", {}).items() if ok is False]
    unjudged = [k for k, ok in s.get("verdicts", {}).items() if ok is None]
    worked = bool(s.get("worked")) and not unjudged
    outside = s.get("verdicts", {}).get("assumption") is False
    return {**{k: s.get(k) for k in COLUMNS}, "learned_limits": s.get("learned_limits"),
            "verdicts": s.get("verdicts"), "worked": worked, "outside": outside,
            "outside_assumption": s.get("outside_assumption"), "identified": s.get("identified"),
            **{k: s.get(k) for k in FIGURES},
            "why": ", ".join([*(f"{k} failed" for k in failed), *(f"{k} not judged" for k in unjudged)]) or None}


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as a markdown table."""
    def cell(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.2f}"
        return "-" if v is None else str(v)

    head = ("profile", "split", *COLUMNS, "outside", "worked", "why")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cell(r.get(k)) for k in head) + " |" for r in rows]
    return "\n".join(lines)


def arguments(ap: argparse.ArgumentParser) -> None:
    from sim_learner.sitl_profiles import FRAMES

    ap.add_argument("--sitl", default=None, metavar="PATH", help="ArduPilot's Rover SITL binary (default: found as "
                    "the tests find it, or $SCMBRIDGE_SITL)")
    ap.add_argument("--frame", choices=tuple(FRAMES), default="skid", help="the family's frame (default skid)")
    ap.add_argument("--profiles", default="heldout", help="dev, heldout, all, N or N..M (default heldout)")
    ap.add_argument("--jobs", type=int, choices=(1, 2), default=1, help="profiles at once (SITL runs in real time)")
    ap.add_argument("--duration", type=float, default=120.0, help="seconds each run may take (the demo's)")
    ap.add_argument("--mission", default=None, help="mission file (default: the paper's S-path)")
    ap.add_argument("--identify", action=argparse.BooleanOptionalAction, default=True, help="the demo's "
                    "--identify (the default): the learner's range measured before each transfer run, not read from "
                    "the profile's parameters; --no-identify reads it")
    ap.add_argument("--out", default=None, help="directory for each profile's runs (default: a temporary one)")


def run(args: argparse.Namespace) -> int:
    from bridge.core.errors import UsageError
    from sim_learner.sitl import find_sitl
    from sim_learner.sitl_profiles import FRAMES, SEED, select

    found = find_sitl()
    binary = args.sitl or (str(found) if found else None)
    if not binary:
        raise UsageError("no ArduPilot SITL binary: --sitl PATH or $SCMBRIDGE_SITL")
    try:
        profiles = select(args.frame, args.profiles)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench-sitl-"))
    t0 = time.monotonic()
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda p: run_profile(p, binary, out / p.name, args.duration, args.mission,
                                                   args.identify), profiles))
    met = sum(1 for r in rows if r["worked"])
    inside = [r for r in rows if not r.get("outside")]
    print(table(rows), file=sys.stderr)
    print(f"{args.frame} {args.profiles}: {met}/{len(rows)} profiles met the goal (strict); "
          f"{len(rows) - len(inside)} outside the method's assumption (stopped and said why); inside it "
          f"{met}/{len(inside)} met the goal", file=sys.stderr)
    emit({"bench": "sitl", "frame": args.frame, "model": FRAMES[args.frame], "profiles": args.profiles,
          "identify": args.identify,
          "seed": SEED, "met": met, "count": len(rows), "rate": round(met / len(rows), 3) if rows else None,
          "outside": len(rows) - len(inside), "rate_inside": round(met / len(inside), 3) if inside else None,
          "goal_rate": 0.9, "wall_s": round(time.monotonic() - t0, 1), "out": str(out),
          "load_avg": [round(x, 2) for x in os.getloadavg()], "rows": rows})
    return 0
