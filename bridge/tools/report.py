"""``scmbridge report run.mcap --out DIR``: the run a recording holds, as figures and the demo's summary figures.

The summary (reached goal, time, the driving time apart from pauses and estops (``driving_s``, ``paused_s``),
mean/max deviation from the mission path, method counts, pairs, missed deadlines,
median solve time) is computed by the demo's own :class:`bridge.tools.demo.Monitor`: the recorded ``state`` and
``status`` messages are fed, in arrival order, to the same subscription callbacks the live monitor runs, so a
recorded demo run gives the figures the live demo printed (``tests/integration/test_record.py`` checks it end to end).

The mission is the last ``mission`` message recorded for the robot, else ``--mission FILE``, else the shipped
S-path (the demo's default). Figures in ``DIR``: ``trajectory.png`` (the learner's poses over the mission),
``deviation.png`` (distance to the path over progress) and ``timeline.png`` (shaded where the mission was paused and
where an estop was latched; commands by method, command-to-applied
latency, solve times and loop jitter, missed deadlines). ``report.json`` holds the summary and the rest.

**Command-to-applied latency** pairs each ``cmd`` with the first ``applied`` echo that names its ``seq``
(``cmd_seq``). Two measures, because the clocks differ:

- *by stamps*: ``applied.stamp - cmd.stamp``. The station stamps ``cmd`` and the driver host stamps ``applied``,
  each with its own ``time.monotonic()``: they are one clock only when both run on one machine (Linux's
  CLOCK_MONOTONIC is per boot). Each node's status names its machine and boot (``Status.host``): equal, the stamps
  are one clock ("same machine"); different, they are not; a recording of nodes older than that field falls back to
  whether the numbers look like one clock (none below -1 ms, median under 1 s), and otherwise discards them.
  ``cmd.stamp`` is the start of the station's tick, before the teacher's solve and the transfer, so this is
  tick-to-vehicle: solve + map + transport + the driver host's gate.
- *by receipt*: the difference of the recorder's receive times, always one clock: publish-to-applied (no solve),
  plus the difference between the two messages' paths to the recorder (station -> recorder vs driver host ->
  recorder).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bridge.core import wire as M
from bridge.core.args import robot_arg
from bridge.core.errors import UsageError
from bridge.core.logsink import print_line
from bridge.tools.mcap_format import Entry, parse_key, read_recording, wire_bytes

#: ``applied`` reasons that carry the seq of the command they executed (a stop command included)
_EXECUTED = ("cmd", "clamped", "stop")


class _Payload:
    def __init__(self, data: bytes) -> None:
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


class _Sample:
    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr = key
        self.payload = _Payload(data)


class FeedSession:
    """Stands in for a ``zenoh.Session`` towards code that only declares subscribers: it keeps their callbacks so
    recorded messages can be fed through the very code that handles them live."""

    def __init__(self) -> None:
        self.subs: list[tuple[str, Callable[[Any], None]]] = []

    def declare_subscriber(self, key: str, callback: Callable[[Any], None]) -> None:
        self.subs.append((str(key), callback))

    def put(self, key: str, data: bytes) -> None:
        import zenoh

        for sub_key, callback in self.subs:
            if sub_key == key or zenoh.KeyExpr(sub_key).intersects(zenoh.KeyExpr(key)):
                callback(_Sample(key, data))


def robots(entries: list[Entry]) -> list[str]:
    """The robots with ``state`` in the recording."""
    return sorted({e.topic.split("/")[1] for e in entries if e.is_wire and parse_key(e.topic)[1] == "state"})


def pick_mission(entries: list[Entry], robot: str, mission_file: str | None) -> tuple[Any, str]:
    """The mission the run followed (see the module docstring) and where it came from."""
    from bridge.core.config import load_mission, mission_from_spec

    key = M.key(robot, "mission")
    recorded = [e for e in entries if e.topic == key]
    if recorded:
        spec = recorded[-1].message()
        extra = f" (the last of {len(recorded)})" if len(recorded) > 1 else ""
        return mission_from_spec(spec), f"recorded on {key}{extra}"
    if mission_file:
        return load_mission(mission_file), f"file {mission_file}"
    return load_mission(None), "the shipped paper-s-path (no mission recorded, no --mission)"


def demo_summary(entries: list[Entry], robot: str, mission: Any) -> tuple[dict | None, np.ndarray]:
    """The demo's summary (``Monitor.summary``) of the recorded run, and the trajectory ``(K, 3)``."""
    from bridge.tools.demo import Monitor

    feed = FeedSession()
    mon = Monitor(feed, robot)
    for e in entries:
        if e.is_wire and e.topic.split("/")[1] == robot:
            feed.put(e.topic, wire_bytes(e, {})[1])
    summary = mon.summary(mission)
    if summary is None:
        traj = np.array([s[1:] for s in mon.states]) if mon.states else np.zeros((0, 3))
        return None, traj
    return summary, summary.pop("_traj")


def _stats_ms(x: list[float]) -> dict[str, float] | None:
    if not x:
        return None
    a = np.asarray(x) * 1e3
    return {"median": round(float(np.median(a)), 3), "p99": round(float(np.percentile(a, 99)), 3),
            "max": round(float(a.max()), 3), "min": round(float(a.min()), 3)}


def machines(entries: list[Entry], robot: str) -> dict[str, Any]:
    """Where the station and the driver host ran, from their statuses' ``host`` (machine and boot): ``same`` True
    when both are known and equal (one monotonic clock), False when both are known and differ, None when a status
    does not say (a node older than the field)."""
    hosts: dict[str, str | None] = {}
    for node in ("station", "driver"):
        said = [st.host for _, st in status_series(entries, robot, node) if st.host]
        hosts[node] = said[-1] if said else None
    known = hosts["station"] is not None and hosts["driver"] is not None
    return {**hosts, "same": (hosts["station"] == hosts["driver"]) if known else None}


def command_latency(entries: list[Entry], robot: str, same_machine: bool | None = None,
                    ) -> tuple[dict[str, Any], list[tuple[float, float, float]]]:
    """Command-to-applied latency (see the module docstring): figures, and ``(t_ns, by_stamps_s, by_receipt_s)``
    per command. ``same_machine``: what the nodes' statuses say (None: unknown, judged from the numbers)."""
    kc, ka = M.key(robot, "cmd"), M.key(robot, "applied")
    cmds: dict[int, list[tuple[int, float]]] = {}
    first_applied: dict[int, tuple[int, float]] = {}
    for e in entries:
        if e.topic == kc:
            c = e.message()
            cmds.setdefault(c.seq, []).append((e.log_time, c.stamp))
        elif e.topic == ka:
            a = e.message()
            if a.cmd_seq is not None and a.reason in _EXECUTED and a.cmd_seq not in first_applied:
                first_applied[a.cmd_seq] = (e.log_time, a.stamp)
    rows = []
    for seq, (t_a, stamp_a) in first_applied.items():
        if seq not in cmds:
            continue  # the command itself was not recorded (before the recorder started)
        t_c, stamp_c = min(cmds[seq], key=lambda c: abs(c[0] - t_a))  # a restarted station reuses seqs
        if abs(t_a - t_c) > 5e9:
            continue
        rows.append((t_c, stamp_a - stamp_c, (t_a - t_c) / 1e9))
    rows.sort()
    by_stamps = [r[1] for r in rows]
    looks_one = bool(by_stamps) and min(by_stamps) > -1e-3 and float(np.median(by_stamps)) < 1.0
    one_clock = bool(by_stamps) and (looks_one if same_machine is None else same_machine)
    out = {"commands": sum(len(v) for v in cmds.values()), "paired": len(rows),
           "by_stamps_ms": _stats_ms(by_stamps) if one_clock else None,
           "stamps_one_clock": one_clock,
           "by_receipt_ms": _stats_ms([r[2] for r in rows]),
           "note": "by_stamps: applied.stamp - cmd.stamp, from the station's tick start (before its solve) to the "
                   "driver host applying it; valid only when the station and the driver host share a monotonic clock "
                   "(one machine). by_receipt: the recorder's receive times of cmd and applied (one clock; no solve, "
                   "plus the difference of the two paths to the recorder)"}
    return out, rows


def status_series(entries: list[Entry], robot: str, node: str) -> list[tuple[int, M.Status]]:
    key = M.status_key(robot, node)
    return [(e.log_time, e.message()) for e in entries if e.topic == key]


def episodes(entries: list[Entry], robot: str) -> dict[str, list[tuple[int, int]]]:
    """When the mission was paused (the station's status ``paused``) and when an estop was latched (the driver host's
    typed reason ``estop``, its state for a host older than the field): each a list of ``(start, end)`` log times
    (ns), an episode still on at the recording's end closed there. The timeline shades them."""
    end = entries[-1].log_time if entries else 0
    tests = {"paused": ("station", lambda st: st.state == "paused"),
             "estop": ("driver", lambda st: (st.reason == "estop") if st.reason is not None else st.state == "estop")}
    out: dict[str, list[tuple[int, int]]] = {}
    for name, (node, on) in tests.items():
        spans, since = [], None
        for t, st in status_series(entries, robot, node):
            if on(st) and since is None:
                since = t
            elif not on(st) and since is not None:
                spans.append((since, t))
                since = None
        if since is not None:
            spans.append((since, end))
        out[name] = spans
    return out


def _figures(out: Path, entries: list[Entry], robot: str, mission: Any, traj: np.ndarray,
             latency_rows: list[tuple[float, float, float]], one_clock: bool) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim_learner.figures import draw_mission

    files = []
    t0 = entries[0].log_time if entries else 0

    def secs(t_ns: float) -> float:
        return (t_ns - t0) / 1e9

    fig, ax = plt.subplots(figsize=(9, 4))
    draw_mission(ax, mission)
    if len(traj):
        ax.plot(traj[:, 0], traj[:, 1], color="tab:blue", label=f"{robot} (recorded state)")
        ax.plot(traj[0, 0], traj[0, 1], "o", color="tab:blue", ms=5)
    # beside the axes, never over an obstacle or the path
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    ax.set_title(f"recorded run: {robot} on {mission.name}")
    fig.tight_layout()
    files.append(out / "trajectory.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 3.5))
    if len(traj):
        proj = [mission.path.project(p[:2]) for p in traj]
        ax.plot([100 * s / mission.path.length for s, _ in proj], [100 * d for _, d in proj], color="tab:blue")
    ax.set_xlabel("progress along the path (%)")
    ax.set_ylabel("deviation from the path (cm)")
    ax.set_title("deviation over progress")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    files.append(out / "deviation.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    fig, axs = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    kc = M.key(robot, "cmd")
    by_method: dict[str, list[float]] = {}
    for e in entries:
        if e.topic == kc:
            by_method.setdefault(e.message().method, []).append(secs(e.log_time))
    for method, ts in sorted(by_method.items()):
        axs[0].step(ts, np.arange(1, len(ts) + 1), where="post", label=method)
    axs[0].set_ylabel("commands sent")
    axs[0].set_title("commands by method (cmd)")
    if by_method:
        axs[0].legend(fontsize=8, ncol=4)
    if latency_rows:
        t = [secs(r[0]) for r in latency_rows]
        if one_clock:
            axs[1].plot(t, [1e3 * r[1] for r in latency_rows], ".", ms=3,
                        label="by stamps: station tick (before the solve) to applied")
        axs[1].plot(t, [1e3 * r[2] for r in latency_rows], ".", ms=3, alpha=0.6,
                    label="by the recorder's receipt of cmd and applied")
        axs[1].legend(fontsize=8)
    axs[1].set_ylabel("ms")
    axs[1].set_title("command to applied latency")
    station, driver = status_series(entries, robot, "station"), status_series(entries, robot, "driver")
    for series, name, keys in ((station, "station", ("solve_median", "solve_max")),
                               (driver, "driver", ("jitter_p99", "telemetry_age"))):
        for k in keys:
            # a driver host with no pose yet reports telemetry_age 1e9 ms ("never"): not a point on this scale
            pts = [(secs(t), s.latencies_ms[k]) for t, s in series if s.latencies_ms.get(k, 1e9) < 1e8]
            if pts:
                axs[2].plot(*zip(*pts), marker=".", label=f"{name} {k}")
    axs[2].set_ylabel("ms")
    axs[2].set_yscale("symlog", linthresh=1.0)
    axs[2].set_title("solve time (station), loop jitter and telemetry age (driver host), from status")
    if axs[2].lines:
        axs[2].legend(fontsize=8, ncol=2)
    for series, name in ((station, "station"), (driver, "driver host")):
        pts = [(secs(t), s.counters.get("missed_deadlines", 0)) for t, s in series]
        if pts:
            axs[3].step(*zip(*pts), where="post", label=name)
    axs[3].set_ylabel("count")
    axs[3].set_title("missed deadlines (status counters)")
    axs[3].set_xlabel("time since the first recorded message (s)")
    if axs[3].lines:
        axs[3].legend(fontsize=8)
    marks = episodes(entries, robot)
    for name, color, label in (("paused", "tab:orange", "mission paused"), ("estop", "tab:red", "estop latched")):
        for k, (a, b) in enumerate(marks[name]):
            for i, ax_ in enumerate(axs):
                ax_.axvspan(secs(a), secs(b), color=color, alpha=0.15 if name == "paused" else 0.25, lw=0,
                            label=label if i == 0 and k == 0 else None)
    if marks["paused"] or marks["estop"]:
        axs[0].legend(fontsize=8, ncol=4)
    fig.tight_layout()
    files.append(out / "timeline.png")
    fig.savefig(files[-1], dpi=110)
    plt.close(fig)
    return files


def report(files: list[str], out: Path, robot: str | None = None, mission_file: str | None = None,
           figures: bool = True) -> dict[str, Any]:
    """Everything ``report.json`` holds; draws the figures into ``out``. ``ValueError`` when the recording has no
    run to report (no state, or several robots and none chosen)."""
    entries, rec = read_recording(files)
    found = robots(entries)
    if robot is None:
        if len(found) != 1:
            raise ValueError(f"the recording has state for {len(found)} robots ({', '.join(found) or 'none'}): "
                             "choose one with --robot" if found else "the recording has no state message")
        robot = found[0]
    elif robot not in found:
        raise ValueError(f"no state of robot {robot!r} in the recording (robots: {', '.join(found) or 'none'})")
    mission, mission_source = pick_mission(entries, robot, mission_file)
    summary, traj = demo_summary(entries, robot, mission)
    where = machines(entries, robot)
    latency, rows = command_latency(entries, robot, where["same"])
    per_topic = Counter(e.topic for e in entries)
    result = {
        "summary": summary, "robot": robot, "mission": {"name": mission.name, "source": mission_source},
        "files": [str(f) for f in files], "truncated": rec.truncated,
        "messages": dict(sorted(per_topic.items())),
        "duration_s": round((entries[-1].log_time - entries[0].log_time) / 1e9, 3) if entries else 0.0,
        "cmd_to_applied": latency, "machines": where,
    }
    if summary is None:
        result["note"] = "no station status recorded: the demo's summary needs the station's counters"
    out.mkdir(parents=True, exist_ok=True)
    if figures:
        result["figures"] = [str(p) for p in _figures(out, entries, robot, mission, traj, rows,
                                                      latency["stamps_one_clock"])]
    (out / "report.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("files", nargs="+", help="MCAP file(s) of one recording, in order")
    ap.add_argument("--out", required=True, help="directory for report.json and the figures")
    ap.add_argument("--robot", type=robot_arg, default=None,
                    help="the robot to report (needed when several were recorded)")
    ap.add_argument("--mission", default=None, help="mission file when the recording holds no mission message")
    ap.add_argument("--no-figures", action="store_true", help="only report.json and the summary")


def run(args: argparse.Namespace) -> int:
    for f in args.files:
        if not Path(f).is_file():
            raise UsageError(f"{f}: no such file")
    out = Path(args.out)
    try:
        result = report(args.files, out, args.robot, args.mission, figures=not args.no_figures)
    except ValueError as exc:
        print(f"scmbridge report: error: {exc}", file=sys.stderr)
        return 1
    for t in result["truncated"]:
        print(f"note: {t} (read up to its last complete chunk)", file=sys.stderr)
    print_line("summary: " + json.dumps(result["summary"]))
    for g in (result["summary"] or {}).get("guard_stops", []):  # when and where a guard of the station's stopped it
        where = f" at ({g['x']}, {g['y']})" if g["x"] is not None else ""
        print(f"stopped by the station's guard {g['reason']}" + (f" {g['t_s']} s into the run" if g["t_s"] is not None
                                                                 else "") + where + f": {g['text']}")
    lat = result["cmd_to_applied"]
    parts = [f"{label} median {lat[k]['median']} ms, p99 {lat[k]['p99']} ms" for k, label in
             (("by_stamps_ms", "by stamps (from the station's tick, solve included)"),
              ("by_receipt_ms", "by the recorder's receipt")) if lat[k]]
    if parts:
        same = result["machines"]["same"]
        where = (" (station and driver host on the same machine)" if same else
                 " (station and driver host on different machines: their stamps are not one clock)" if same is False
                 else "" if lat["stamps_one_clock"] else
                 " (the stamps do not look like one clock; the recorded statuses do not say the nodes' machines)")
        print(f"command to applied over {lat['paired']} commands: " + "; ".join(parts) + where)
    print(f"report: {out / 'report.json'}" + (f"; figures: {', '.join(result['figures'])}" if "figures" in result
                                              else ""))
    return 0 if result["summary"] is not None else 1
