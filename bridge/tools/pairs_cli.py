"""``scmbridge pairs show|plot``: see what a station has learned (its refined command pairs and the learner's limits).

Two sources, one view:

- ``--robot R [Zenoh options]`` asks the running station: a Zenoh ``get`` on ``scm/R/pairs`` (retried until
  ``--timeout``, since a fresh session needs a moment to reach its peer) answered with the refined pairs and the
  learned limits (``bridge.core.wire.Pairs``); meanwhile it listens on ``scm/R/cmd`` (and ``scm/R/teacher``) for up to a
  second, for the method and the mapping region of the latest command. The ``Pairs`` reply carries no command
  bounds nor grid: they come from ``--config station.toml``, the station's own configuration (its defaults
  without it). When no station answers the command ends with one line naming the robot and the endpoints tried,
  and exit status 2.
- ``--store FILE`` reads a pair store file (``scmbridge station --store``, the demo's ``pairs.bin``) offline; it
  carries its bounds and grid.

``show`` prints a table (id, cluster size, teacher (v, omega), learner (v, omega)), the learned limits (box and
hull), how many grid cells are configured, the cells re-learned because their learner changed (``[transfer] adapt``:
how often and when last, docs/PAPER.md "Beyond the paper") and, live, the latest command; ``--json`` prints the same
as one JSON object for machines. ``plot --out FILE.png`` draws the paper's pair of command-domain figures
(:func:`sim_learner.plots.command_domains_figure`): the teacher domain with its bounds, the learned limits, the refined
pairs' teacher parts and their Delaunay triangulation, and the learner domain with its bounds, the grid and the
pairs' learner parts, with the region that mapped the latest command highlighted on both. :func:`pairs_figure`
draws the same from a store file, for the demo's output.

The triangulation drawn is the one the station's mappers use (``transfer.mappers``): Delaunay on the refined
pairs' teacher parts normalised by the teacher's bounds, in pair-id order. So a region (``Command.region``: the
quadrilateral of two adjacent triangles for ``scm``, one triangle for ``barycentric``) is made of drawn triangles.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bridge.core import wire as M
from bridge.core.args import positive_float, robot_arg
from bridge.core.errors import UsageError
from bridge.core.logsink import print_line
from bridge.core.paths import STORE_FILE, read_bounded
from bridge.nodes.node import add_zenoh_args, endpoints_tried, zenoh_config
from bridge.nodes.station_tags import untagged
from transfer.domain import Bounds
from transfer.store import PairStore

#: how long ``--robot`` listens for the latest command once the station has answered
COMMAND_WAIT_S = 1.0
#: after a command, how long to wait for the teacher command it was mapped from (published right after it)
TEACHER_WAIT_S = 0.2


class PairsError(UsageError):
    """A problem the user has to act on (no station, unreadable store); ``str()`` is the one line to print."""


@dataclass(frozen=True)
class LatestCommand:
    """The latest ``cmd`` of the station: how it was obtained and, for a mapped one, the region that mapped it."""

    seq: int
    method: str
    v: float
    omega: float
    region: tuple[int, ...]
    teacher: tuple[float, float] | None = None  # the teacher's own command of the same tick, when one came


@dataclass
class Learned:
    """What a station has learned, whichever the source: refined pairs (command units), limits, bounds, grid."""

    source: str
    ids: NDArray[np.int64]
    versions: NDArray[np.int64]
    counts: NDArray[np.int64]
    teacher: NDArray[np.float64]  # (n, 2) teacher parts, teacher units
    learner: NDArray[np.float64]  # (n, 2) learner parts, learner units
    teacher_bounds: Bounds
    learner_bounds: Bounds
    grid: tuple[int, int]
    limits_box: Bounds | None
    hull: NDArray[np.float64]  # (k, 2) counter-clockwise, teacher units
    bounds_from: str  # where the bounds and grid come from: the store itself, a configuration file, the defaults
    robot: str | None = None
    raw_pairs: int | None = None
    k_min: int | None = None
    latest: LatestCommand | None = None
    warnings: list[str] = field(default_factory=list)
    #: cells re-learned because their learner changed (``[transfer] adapt``): (id, how often, when: the stamp given
    #: to the store, wall-clock seconds from a station; None: unknown), the most recent last
    changed: list[tuple[int, int, float | None]] = field(default_factory=list)
    #: the yaw-rate sides' curvatures learned at the full lock (rad/m, lower and upper; None: none yet), from a store
    curvature: tuple[float | None, float | None] | None = None

    @property
    def cells(self) -> int:
        """Cells of the refinement grid."""
        return self.grid[0] * self.grid[1]

    def triangles(self) -> NDArray[np.int64] | None:
        """The Delaunay triangles ``(m, 3)`` (indices into the pairs) the station's mappers build: on the teacher
        parts normalised by the teacher's bounds; None while fewer than three pairs are not collinear."""
        from scipy.spatial import Delaunay, QhullError

        if len(self.ids) < 3:
            return None
        try:
            return np.asarray(Delaunay(self.teacher_bounds.normalise(self.teacher)).simplices, dtype=np.int64)
        except QhullError:
            return None

    def summary(self) -> str:
        """One line: how many pairs and cells, and the latest command with its region."""
        n = len(self.ids)
        out = f"{n} refined pairs, {n}/{self.cells} cells configured"
        if self.latest is not None:
            c = self.latest
            out += f"; latest command: {c.method}" + (f", region {list(c.region)}" if c.region else "")
        return out

    def region_points(self) -> tuple[list[int], list[int]]:
        """The latest command's region split into (ids among the pairs, ids missing from them)."""
        if self.latest is None:
            return [], []
        have = {int(i) for i in self.ids}
        region = list(self.latest.region)
        return [i for i in region if i in have], [i for i in region if i not in have]

    def as_json(self) -> dict[str, Any]:
        """The machine-readable view (``show --json``)."""
        latest = None
        if self.latest is not None:
            c = self.latest
            latest = {"seq": c.seq, "method": c.method, "v": c.v, "omega": c.omega, "region": list(c.region),
                      "teacher": list(c.teacher) if c.teacher is not None else None}
        return {
            "source": self.source,
            "robot": self.robot,
            "pairs": [{"id": int(i), "version": int(v), "count": int(n), "teacher": [float(t[0]), float(t[1])],
                       "learner": [float(u[0]), float(u[1])]}
                      for i, v, n, t, u in zip(self.ids, self.versions, self.counts, self.teacher, self.learner)],
            "limits": {"box": self.limits_box.as_list() if self.limits_box is not None else None,
                       "hull": [[float(a), float(b)] for a, b in self.hull],
                       "curvature": list(self.curvature) if self.curvature is not None else None},
            "cells": {"configured": len(self.ids), "total": self.cells, "grid": list(self.grid)},
            "teacher_bounds": self.teacher_bounds.as_list(),
            "learner_bounds": self.learner_bounds.as_list(),
            "bounds_from": self.bounds_from,
            "raw_pairs": self.raw_pairs,
            "k_min": self.k_min,
            "latest_command": latest,
            "changed_cells": [{"id": i, "count": n, "at": at, "when": when(at)} for i, n, at in self.changed],
            "warnings": list(self.warnings),
        }


# ------------------------------------------------------------------------------------------------- sources
def load_store_file(path: str | Path) -> PairStore:
    """The pair store in ``path``, or :class:`PairsError` saying why it cannot be read."""
    p = Path(path)
    try:
        data = read_bounded(p, STORE_FILE)
    except FileNotFoundError:
        raise PairsError(f"{p}: no such pair store file") from None
    except OSError as exc:
        raise PairsError(f"{p}: cannot read: {exc.strerror or exc}") from None
    try:
        return PairStore.from_bytes(untagged(data))  # (looked at, not driven with: the tag is the station's)
    except ValueError as exc:
        raise PairsError(f"{p}: {exc}") from None


def from_store(store: PairStore, source: str) -> Learned:
    """The view of a pair store (what the station holds in memory, or a file it wrote)."""
    ids, versions, T, L = store.refined_arrays()
    return Learned(
        source=source, ids=ids.astype(np.int64), versions=versions.astype(np.int64),
        counts=store.cells.count.ravel()[ids].astype(np.int64),
        teacher=store.teacher_bounds.denormalise(T).reshape(-1, 2),
        learner=store.learner_bounds.denormalise(L).reshape(-1, 2), teacher_bounds=store.teacher_bounds,
        learner_bounds=store.learner_bounds, grid=store.grid, limits_box=store.limits.box,
        hull=np.asarray(store.limits.hull, dtype=float).reshape(-1, 2), bounds_from="the store",
        raw_pairs=store.raw_count, k_min=store.k_min,
        changed=[(c.id, c.count, c.at) for c in store.changed_cells()],
        curvature=store.limits.known_curvature())


def from_message(msg: M.Pairs, teacher_bounds: Bounds, learner_bounds: Bounds, grid: tuple[int, int],
                 bounds_from: str, source: str, latest: LatestCommand | None = None) -> Learned:
    """The view of a station's ``Pairs`` reply, with the bounds and grid the message does not carry; warns when the
    pairs do not fit them (the station runs with another configuration than the one given)."""
    recs = sorted(msg.pairs, key=lambda r: r.id)
    box = None
    if msg.limits_box is not None:
        try:
            box = Bounds.from_list(msg.limits_box)
        except ValueError:
            box = None
    out = Learned(
        source=source, robot=msg.robot,
        ids=np.array([r.id for r in recs], dtype=np.int64), versions=np.array([r.version for r in recs], np.int64),
        counts=np.array([r.count for r in recs], dtype=np.int64),
        teacher=np.array([[r.teacher_v, r.teacher_omega] for r in recs], dtype=float).reshape(-1, 2),
        learner=np.array([[r.learner_v, r.learner_omega] for r in recs], dtype=float).reshape(-1, 2),
        teacher_bounds=teacher_bounds, learner_bounds=learner_bounds, grid=grid, limits_box=box,
        hull=np.array(msg.limits_hull, dtype=float).reshape(-1, 2), bounds_from=bounds_from, latest=latest,
        changed=[(c.id, c.count, c.at) for c in msg.changed])
    if len(out.ids) and int(out.ids.max()) >= out.cells:
        out.warnings.append(f"pair id {int(out.ids.max())} is beyond the {grid[0]} x {grid[1]} grid of {bounds_from}: "
                            "the station runs with another grid (give its --config)")
    # the store clips every learner part into the station's learner bounds: one outside these is another config
    if len(out.ids) and not np.all(learner_bounds.contains(out.learner, 1e-6)):
        out.warnings.append(f"pairs lie outside the command bounds of {bounds_from}: the station runs with other "
                            "bounds (give its --config); the axes are widened to show them")
    return out


class _Listener:
    """The latest ``cmd`` and the recent ``teacher`` commands, filled by Zenoh callbacks (decode and keep only)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.got_cmd = threading.Event()
        self.cmd: M.Command | None = None
        self.teacher: dict[tuple[int, int], M.TeacherCommand] = {}

    def on_cmd(self, sample: Any) -> None:
        try:
            cmd = M.decode(sample.payload.to_bytes(), M.Command)
        except M.MessageError:
            return
        with self.lock:
            self.cmd = cmd
        self.got_cmd.set()

    def on_teacher(self, sample: Any) -> None:
        try:
            t = M.decode(sample.payload.to_bytes(), M.TeacherCommand)
        except M.MessageError:
            return
        with self.lock:
            self.teacher[(t.epoch, t.seq)] = t
            if len(self.teacher) > 64:
                self.teacher.pop(next(iter(self.teacher)))

    def latest(self) -> LatestCommand | None:
        """The latest command, with the teacher command of the same tick when it has arrived."""
        with self.lock:
            cmd = self.cmd
            t = self.teacher.get((cmd.epoch, cmd.seq)) if cmd is not None else None
        if cmd is None:
            return None
        return LatestCommand(seq=cmd.seq, method=cmd.method, v=cmd.v, omega=cmd.omega, region=tuple(cmd.region),
                             teacher=(t.v, t.omega) if t is not None else None)


def _get_pairs(session: Any, robot: str, deadline: float) -> M.Pairs | None:
    """Query ``scm/<robot>/pairs`` until a station answers or ``deadline`` (monotonic) passes."""
    k = M.Keys(robot).pairs
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        for reply in session.get(k, timeout=min(remaining, 1.0)):
            if reply.ok is None:
                continue
            try:
                return M.decode(reply.ok.payload.to_bytes(), M.Pairs)
            except M.MessageError as exc:
                raise PairsError(f"the station for robot {robot!r} answered on {k} with a malformed reply: {exc}"
                                 ) from None
        time.sleep(min(0.1, max(deadline - time.monotonic(), 0.0)))  # not connected yet, or no station (yet)


def ask_station(args: argparse.Namespace, robot: str, timeout: float,
                command_wait: float = COMMAND_WAIT_S) -> tuple[M.Pairs, LatestCommand | None]:
    """The station's ``Pairs`` reply and its latest command (None if no ``cmd`` came within ``command_wait``).

    The ``cmd`` subscription is declared before the query, so the wait overlaps the connection set-up. If the
    latest command's region names pairs the reply does not hold (they became refined in between), the station is
    asked once more, so the region can be drawn.
    """
    import zenoh

    from bridge.nodes.zsession import open_session

    conf = zenoh_config(args)
    listener = _Listener()
    keys = M.Keys(robot)
    try:
        with open_session(conf) as session:
            session.declare_subscriber(keys.cmd, listener.on_cmd)
            session.declare_subscriber(keys.teacher, listener.on_teacher)
            msg = _get_pairs(session, robot, time.monotonic() + timeout)
            if msg is None:
                raise PairsError(f"no station answered for robot {robot!r} on {keys.pairs} within {timeout:g} s "
                                 f"(tried {endpoints_tried(args)})")
            if listener.got_cmd.wait(command_wait):  # then a moment for the teacher command of the same tick
                t_end = time.monotonic() + TEACHER_WAIT_S
                while ((c := listener.latest()) is not None and c.method != "stop" and c.teacher is None
                       and time.monotonic() < t_end):
                    time.sleep(0.02)
            latest = listener.latest()
            if latest is not None and not set(latest.region) <= {r.id for r in msg.pairs}:
                msg = _get_pairs(session, robot, time.monotonic() + 1.0) or msg
    except zenoh.ZError as exc:
        raise PairsError(f"cannot reach the station for robot {robot!r} (tried {endpoints_tried(args)}): "
                         f"{str(exc).split(' at ')[0].strip()}") from None
    return msg, latest


def gather(args: argparse.Namespace) -> Learned:
    """The view asked for on the command line: the store file, or the running station."""
    if args.store:
        return from_store(load_store_file(args.store), f"pair store {args.store}")
    from bridge.core.config import load_station

    cfg = load_station(args.config)  # a configuration mistake ends here, before any session opens
    robot = args.robot
    bounds_from = f"config {args.config}" if args.config else "the station defaults (no --config)"
    msg, latest = ask_station(args, robot, args.timeout)
    tb, lb, grid = cfg.teacher_bounds.bounds(), cfg.learner_bounds.bounds(), tuple(cfg.transfer.grid)
    if msg.teacher_bounds and msg.learner_bounds and msg.grid:  # a station that says its own bounds and grid
        tb, lb = Bounds.from_list(msg.teacher_bounds), Bounds.from_list(msg.learner_bounds)
        grid, bounds_from = (msg.grid[0], msg.grid[1]), "the station"
    return from_message(msg, tb, lb, grid, bounds_from, f"station for robot {robot!r} ({M.Keys(robot).pairs})",
                        latest)


# ------------------------------------------------------------------------------------------------- outputs
#: a change stamp at or above this is wall-clock seconds (a station's); below, a run's own clock (a simulation's)
WALL_CLOCK_FROM = 1e9


def when(at: float | None) -> str:
    """A cell's change time in words: UTC for a station's wall-clock stamp, seconds for a run's own clock."""
    if at is None:
        return "time unknown"
    if at >= WALL_CLOCK_FROM:
        return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(at))
    return f"t = {at:.1f} s"


def _range(b: Bounds) -> str:
    return f"v [{b.v[0]:.3f}, {b.v[1]:.3f}] m/s, omega [{b.w[0]:+.3f}, {b.w[1]:+.3f}] rad/s"


def table(view: Learned) -> str:
    """The human-readable view (``show``)."""
    lines = [f"what was learned: {view.source}"]
    lines.append(f"{'id':>5} {'count':>6} | {'teacher v':>10} {'teacher w':>10} | {'learner v':>10} {'learner w':>10}")
    for i, n, t, u in zip(view.ids, view.counts, view.teacher, view.learner):
        lines.append(f"{int(i):>5} {int(n):>6} | {t[0]:>10.4f} {t[1]:>+10.4f} | {u[0]:>10.4f} {u[1]:>+10.4f}")
    if not len(view.ids):
        lines.append("  (no refined pair yet)")
    extra = f"; {view.raw_pairs} raw pairs, k_min {view.k_min}" if view.raw_pairs is not None else ""
    lines.append(f"refined pairs: {len(view.ids)}; configured cells: {len(view.ids)} of {view.cells} "
                 f"(grid {view.grid[0]} x {view.grid[1]}){extra}")
    if view.limits_box is not None:
        lines.append(f"learned limits on the teacher domain (box): {_range(view.limits_box)}")
    if view.curvature is not None and any(k is not None for k in view.curvature):
        k_lo, k_hi = ("-" if k is None else f"{k:+.3f}" for k in view.curvature)
        lines.append(f"learned curvature at the full lock: {k_lo} .. {k_hi} rad/m (k_lo v <= omega <= k_hi v: a "
                     "bound of the teacher with [transfer] turn = \"needs-speed\")")
    hull = " ".join(f"({a:.3f}, {b:+.3f})" for a, b in view.hull)
    lines.append(f"learned limits (hull, {len(view.hull)} vertices): {hull or '-'}")
    lines.append(f"teacher bounds: {_range(view.teacher_bounds)}")
    lines.append(f"learner bounds: {_range(view.learner_bounds)}  (bounds and grid from {view.bounds_from})")
    if view.changed:
        lines.append(f"changed cells (their learner no longer answered as their pairs said; re-learned): "
                     f"{len(view.changed)}")
        gw = view.grid[1]
        for i, n, at in view.changed:
            lines.append(f"  cell {i:>4} (v {i // gw}, omega {i % gw} on the grid): re-learned {n}x, last {when(at)}")
    else:
        lines.append("changed cells: none")
    if view.robot is not None:
        c = view.latest
        if c is None:
            lines.append(f"latest command: none within {COMMAND_WAIT_S:g} s on {M.Keys(view.robot).cmd}")
        else:
            region = f", region {list(c.region)}" if c.region else ", no region"
            teacher = f", from teacher ({c.teacher[0]:.3f}, {c.teacher[1]:+.3f})" if c.teacher is not None else ""
            lines.append(f"latest command: {c.method} (v {c.v:.3f} m/s, omega {c.omega:+.3f} rad/s){region}{teacher}")
            missing = view.region_points()[1]
            if missing:
                lines.append(f"  region pairs not in the reply: {missing}")
    lines += [f"warning: {w}" for w in view.warnings]
    return "\n".join(lines)


def draw(view: Learned, out_png: str | Path, region: tuple[int, ...] | list[int] | None = None) -> Path:
    """Write the command-domain figure of ``view`` to ``out_png``; ``region`` (pair ids) overrides the latest
    command's region."""
    from sim_learner.plots import command_domains_figure

    c = view.latest
    if region is None:
        region = view.region_points()[0]
    fig = command_domains_figure(
        ids=view.ids, teacher=view.teacher, learner=view.learner, teacher_bounds=view.teacher_bounds,
        learner_bounds=view.learner_bounds, limits_box=view.limits_box, hull=view.hull, triangles=view.triangles(),
        grid=view.grid, region=list(region),
        teacher_cmd=c.teacher if c is not None and c.teacher is not None and c.method != "stop" else None,
        learner_cmd=(c.v, c.omega) if c is not None and c.method != "stop" else None,
        title=f"{view.source}: {view.summary()}")
    out = Path(out_png)
    import matplotlib.pyplot as plt

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=120)
    except (ValueError, OSError) as exc:
        raise PairsError(f"{out}: cannot write the figure: {exc}") from None
    finally:
        plt.close(fig)
    return out


def pairs_figure(store_path: str | Path, out_png: str | Path, region: list[int] | tuple[int, ...] | None = None
                 ) -> Path:
    """Draw what a pair store file holds (the demo calls this at its end with its ``pairs.bin``): the same figure as
    ``scmbridge pairs plot --store``, with ``region`` (refined-pair ids, e.g. a ``Command.region``) highlighted."""
    return draw(from_store(load_store_file(store_path), f"pair store {Path(store_path).name}"), out_png,
                None if region is None else [int(i) for i in region])


def _source(ap: argparse.ArgumentParser) -> None:
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--robot", type=robot_arg, help="ask the running station of this robot over Zenoh")
    src.add_argument("--store", help="read a pair store file instead (offline; it carries its bounds)")
    ap.add_argument("--config", help="the station's TOML: command bounds and grid for --robot (default: the "
                                     "station defaults)")
    ap.add_argument("--timeout", type=positive_float, default=3.0,
                    help="seconds to wait for the station's answer (default 3)")
    add_zenoh_args(ap)


def arguments_show(ap: argparse.ArgumentParser) -> None:
    _source(ap)
    ap.add_argument("--json", action="store_true", help="one JSON object instead of the table")


def arguments_plot(ap: argparse.ArgumentParser) -> None:
    _source(ap)
    ap.add_argument("--out", required=True, help="the figure to write (FILE.png)")


def run_show(args: argparse.Namespace) -> int:
    """Print what a station learned: one row per refined pair (id = its learner grid cell, cluster size, teacher
    and learner commands), the learned limits, the configured cells and, live, how the latest command was
    obtained. --robot asks the running station over Zenoh; --store reads a pair store file offline."""
    view = gather(args)
    print_line(json.dumps(view.as_json()) if args.json else table(view))
    return 0


def run_plot(args: argparse.Namespace) -> int:
    """Draw the paper's command-domain figures of what a station learned: the teacher domain with the learned
    limits, the refined pairs and their Delaunay triangulation, and the learner domain with the refinement grid;
    live, the region that mapped the latest command is shaded."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise PairsError("plot needs matplotlib (pip install 'scmbridge[sims]')") from None
    view = gather(args)
    out = draw(view, args.out)
    print(f"figure: {out} ({view.summary()})")
    for w in view.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0


__all__ = ["Learned", "LatestCommand", "PairsError", "draw", "from_message", "from_store", "pairs_figure",
           "table", "when"]
