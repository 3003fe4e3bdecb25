"""Drawing command domains the way the paper's figures do (Sections 4-5), shared by the station-side tools and the
simulations.

The station side (``scmbridge pairs plot``, the demo's figure of what was learned) must not import the simulator,
so the helpers both need live here: the command box, the colour-coded refined pairs (one colour per pair, the same
on both domains, so the eye matches a teacher point to its learner point) and the two-panel figure of
:func:`command_domains_figure`: (a) the teacher command domain with the teacher's bounds, the learner's limits
learned on it (box and convex hull), the refined pairs' teacher parts and their Delaunay triangulation; (b) the
learner command domain with the learner's bounds, the refinement grid (configured cells shaded) and the refined
pairs' learner parts; on both, the mapping region of the current command and the command itself (red cross).

matplotlib is imported here, at the top: import this module only where a figure is wanted (the station and the
driver host run without matplotlib). Importing it chooses no backend: each function that makes a figure calls
:func:`headless` first, so a process that imports it for its helpers keeps its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Polygon, Rectangle
from numpy.typing import ArrayLike, NDArray

from transfer.domain import Bounds


def headless() -> None:
    """Draw on Agg from here on: the figures are written to files, never shown, and a machine without a display
    (a lab's base station, CI) must not try to open one."""
    matplotlib.use("Agg")


REGION_COLOR = "tab:orange"
LIMITS_COLOR = "tab:red"


def draw_box(ax: Axes, b: Bounds, **kw) -> None:
    """Outline the command box ``b`` (keyword arguments go to the Rectangle: ``ec``, ``ls``, ``label``...)."""
    ax.add_patch(Rectangle((b.v[0], b.w[0]), b.v[1] - b.v[0], b.w[1] - b.w[0], fill=False, **kw))


def pair_colors(n: int) -> NDArray[np.float64]:
    """One colour per refined pair (viridis in pair order): pair k has the same colour on both domains."""
    return plt.cm.viridis(np.linspace(0, 1, max(n, 1)))[:n]


def draw_pairs(ax_t: Axes, ax_l: Axes, T: ArrayLike, L: ArrayLike, **kw) -> None:
    """Scatter the refined pairs' teacher parts ``T`` on ``ax_t`` and learner parts ``L`` on ``ax_l`` (``(n, 2)``
    arrays in whatever units the axes use), colour-coded so a pair is recognisable across the two domains."""
    T, L = np.asarray(T, dtype=float).reshape(-1, 2), np.asarray(L, dtype=float).reshape(-1, 2)
    colors = pair_colors(len(T))
    kw.setdefault("s", 14)
    ax_t.scatter(T[:, 0], T[:, 1], c=colors, **kw)
    ax_l.scatter(L[:, 0], L[:, 1], c=colors, **kw)


def _frame(ax: Axes, bounds: Bounds, pts: NDArray[np.float64], title: str) -> None:
    """Axes limits: the command bounds with a margin, widened to whatever is drawn outside them (points from a
    station configured with other bounds than the ones given here stay visible)."""
    lo = np.minimum(bounds.lo, pts.min(axis=0)) if len(pts) else bounds.lo
    hi = np.maximum(bounds.hi, pts.max(axis=0)) if len(pts) else bounds.hi
    pad = 0.05 * (hi - lo)
    ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
    ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
    ax.set_xlabel("v (m/s)")
    ax.set_ylabel("omega (rad/s)")
    ax.set_title(title, fontsize=10)
    ax.grid(False)


def _region(ax: Axes, pts: NDArray[np.float64], ids: Sequence[int], label: str) -> None:
    """Shade the mapping region (its vertices in the order the mapper gave: counter-clockwise) and name its pairs."""
    if len(pts) >= 3:
        ax.add_patch(Polygon(pts, closed=True, fc=REGION_COLOR, ec=REGION_COLOR, alpha=0.35, lw=2, label=label,
                             zorder=3))
    ax.scatter(pts[:, 0], pts[:, 1], s=60, facecolors="none", edgecolors=REGION_COLOR, linewidths=2, zorder=5,
               label=None if len(pts) >= 3 else label)
    for (x, y), i in zip(pts, ids):
        ax.annotate(str(i), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, color="saddlebrown",
                    zorder=6)


def _teacher_side(ax: Axes, T: NDArray[np.float64], teacher_bounds: Bounds, limits_box: Bounds | None,
                  hull: NDArray[np.float64] | None, triangles: NDArray[np.int64] | None) -> None:
    """The teacher domain's layers: its bounds, the learned limits (box, hull), the triangulation of the pairs."""
    draw_box(ax, teacher_bounds, ec="0.3", lw=1.2, label="teacher bounds")
    if limits_box is not None:
        draw_box(ax, limits_box, ec=LIMITS_COLOR, lw=1.5, label="learned limits (box)")
    if hull is not None and len(hull) >= 3:
        ax.add_patch(Polygon(hull, closed=True, fill=True, fc=LIMITS_COLOR, alpha=0.07, ec=LIMITS_COLOR, ls="--",
                             lw=1.2, label="learned limits (hull)"))
    if triangles is not None and len(triangles):
        ax.triplot(T[:, 0], T[:, 1], triangles, color="0.6", lw=0.6, zorder=1)
        ax.plot([], [], color="0.6", lw=0.6, label="Delaunay triangulation")


def _learner_grid(ax: Axes, ids: NDArray[np.int64], learner_bounds: Bounds, grid: tuple[int, int]) -> None:
    """The refinement grid on the learner domain, the configured cells (cell id ``i * n_omega + j``) shaded."""
    gv, gw = grid
    span = learner_bounds.span
    for i in range(1, gv):
        ax.axvline(learner_bounds.v[0] + span[0] * i / gv, color="0.88", lw=0.6, zorder=0)
    for j in range(1, gw):
        ax.axhline(learner_bounds.w[0] + span[1] * j / gw, color="0.88", lw=0.6, zorder=0)
    for n, cid in enumerate(int(c) for c in ids if 0 <= c < gv * gw):
        i, j = divmod(cid, gw)
        x0, y0 = learner_bounds.denormalise([i / gv, j / gw])
        ax.add_patch(Rectangle((x0, y0), span[0] / gv, span[1] / gw, fc="tab:green", alpha=0.08, ec="none",
                               zorder=0, label="configured cell" if n == 0 else None))


#: what the command-domain figure shows, in its own words (README.md, "Glossary")
CAPTION = ("A refined pair (one colour on both sides) is the mean of the raw pairs of one cell of the learner's grid "
           "(a cell is configured once it holds k_min). A mapping region is a quadrilateral of four refined pairs, "
           "two neighbouring Delaunay triangles, simple on both sides: a teacher command inside it is mapped by the "
           "SC map between the two quadrilaterals (scm) or by linear interpolation on its triangle (barycentric). "
           "The learned limits bound what the teacher may ask.")


def command_domains_figure(
    *,
    ids: Sequence[int],
    teacher: ArrayLike,
    learner: ArrayLike,
    teacher_bounds: Bounds,
    learner_bounds: Bounds,
    limits_box: Bounds | None = None,
    hull: ArrayLike | None = None,
    triangles: ArrayLike | None = None,
    grid: tuple[int, int] | None = None,
    region: Sequence[int] = (),
    teacher_cmd: ArrayLike | None = None,
    learner_cmd: ArrayLike | None = None,
    title: str = "",
) -> Figure:
    """The paper's command-domain plots of what was learned (see the module docstring), in three panels: (a) the
    teacher command domain over the teacher's whole bounds, (a') the same zoomed onto the learned limits (where the
    pairs and the mapping regions are: the learner usually spans a small part of the teacher's range), (b) the
    learner command domain.

    ``ids``, ``teacher``, ``learner``: the refined pairs (ids, ``(n, 2)`` teacher and learner parts in command
    units); ``triangles``: ``(m, 3)`` indices into them (the Delaunay triangulation of the teacher parts);
    ``grid``: the refinement grid (cell id = ``i * n_omega + j``, the refined pair ids); ``region``: pair ids of the
    mapping region of the current command, in the mapper's order (ids not among ``ids`` are skipped);
    ``teacher_cmd``/``learner_cmd``: the current teacher command and the learner command it was mapped to.
    """
    ids_a = np.asarray(ids, dtype=np.int64).reshape(-1)
    T = np.asarray(teacher, dtype=float).reshape(-1, 2)
    L = np.asarray(learner, dtype=float).reshape(-1, 2)
    H = np.asarray(hull, dtype=float).reshape(-1, 2) if hull is not None else None
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3) if triangles is not None else None
    headless()
    fig, (ax_t, ax_z, ax_l) = plt.subplots(1, 3, figsize=(16.5, 5.8), gridspec_kw={"width_ratios": [1, 1, 1]})

    for ax in (ax_t, ax_z):
        _teacher_side(ax, T, teacher_bounds, limits_box, H, tri)
    draw_box(ax_l, learner_bounds, ec="0.3", lw=1.2, label="learner bounds")
    if grid is not None:
        _learner_grid(ax_l, ids_a, learner_bounds, grid)
    pair_kw = {"s": 22, "edgecolors": "k", "linewidths": 0.5, "zorder": 4}
    draw_pairs(ax_t, ax_l, T, L, **pair_kw)
    ax_z.scatter(T[:, 0], T[:, 1], c=pair_colors(len(T)), **pair_kw)
    for ax in (ax_z, ax_l):  # a legend entry for the colour-coded pairs
        ax.scatter([], [], c=[pair_colors(3)[1]], label=f"refined pairs ({len(T)}), colour-coded", **pair_kw)

    pos = {int(i): k for k, i in enumerate(ids_a)}
    known = [int(i) for i in region if int(i) in pos]
    if known:
        rows = [pos[i] for i in known]
        for ax, P in ((ax_t, T), (ax_z, T), (ax_l, L)):
            _region(ax, P[rows], known if ax is not ax_t else [], f"mapping region {known}")
    for ax, c, name in ((ax_t, teacher_cmd, "teacher"), (ax_z, teacher_cmd, "teacher"), (ax_l, learner_cmd, "learner")):
        if c is not None:
            c = np.asarray(c, dtype=float)
            ax.scatter([c[0]], [c[1]], marker="x", s=90, c="red", linewidths=2.2, zorder=7, label=f"{name} command")

    drawn_t = np.vstack([T, H]) if H is not None else T
    _frame(ax_t, teacher_bounds, drawn_t, "(a) teacher command domain")
    zoom = limits_box if limits_box is not None else teacher_bounds
    if len(T):
        zlo, zhi = np.minimum(zoom.lo, T.min(axis=0)), np.maximum(zoom.hi, T.max(axis=0))
        zoom = Bounds((float(zlo[0]), float(zhi[0])), (float(zlo[1]), float(zhi[1])))
    _frame(ax_z, zoom, np.zeros((0, 2)), "(a') teacher command domain, the learned limits")
    _frame(ax_l, learner_bounds, L, "(b) learner command domain")
    ax_z.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3, fontsize=7, frameon=False)
    ax_l.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=7, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.text(0.5, 0.008, CAPTION, ha="center", va="bottom", fontsize=7.5, wrap=True)
    return fig


__all__ = ["command_domains_figure", "draw_box", "draw_pairs", "pair_colors"]
