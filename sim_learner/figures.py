"""Figures like the paper's: trajectories, deviation over progress, command domains with pairs, error maps."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Circle

from sim_learner.plots import draw_box as _box  # (shared with the station-side `scmbridge pairs plot`)
from sim_learner.plots import draw_pairs, headless
from sim_learner.runs import deviation_profile
from transfer.domain import Bounds
from transfer.store import PairStore

COLORS = {"teacher": "tab:green", "scm": "tab:blue", "baseline": "tab:red", "baseline_true": "tab:orange"}
#: grid-figure codes of the policy's methods (anything else: 0, with "direct")
METHOD_CODES = {"direct": 0, "perturb": 1, "barycentric": 1.5, "scm": 2}


def draw_mission(ax, world) -> None:
    p = world.path.points
    ax.plot(p[:, 0], p[:, 1], "k--", lw=1, label="desired path")
    for ox, oy, r in world.obstacles:
        ax.add_patch(Circle((ox, oy), r, color="0.5", alpha=0.6))
    ax.plot(*world.goal, "k*", ms=12)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def _pairs(ax_t, ax_l, store: PairStore, normalised: bool) -> None:
    _, _, T, L = store.refined_arrays()
    if not normalised:
        T = store.teacher_bounds.denormalise(T)
        L = store.learner_bounds.denormalise(L)
    draw_pairs(ax_t, ax_l, T, L)


def mpc_figures(out: Path, world, runs, store: PairStore, true_box: Bounds, TB: Bounds, LB: Bounds) -> list[str]:
    headless()
    files = []
    fig, ax = plt.subplots(figsize=(9, 4))
    draw_mission(ax, world)
    for r in runs:
        P = np.array(r.poses)
        ax.plot(P[:, 0], P[:, 1], color=COLORS.get(r.name), label=f"{r.name} ({'goal' if r.reached else 'no goal'})")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("MPC transfer: trajectories")
    fig.tight_layout()
    fig.savefig(out / "mpc_trajectories.png", dpi=120)
    plt.close(fig)
    files.append("mpc_trajectories.png")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for r in runs:
        prog, dev = deviation_profile(r.poses, world)
        ax.plot(prog, dev, color=COLORS.get(r.name), label=r.name)
    ax.set_xlabel("task progress")
    ax.set_ylabel("deviation from path (m)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "mpc_deviation.png", dpi=120)
    plt.close(fig)
    files.append("mpc_deviation.png")

    fig, axs = plt.subplots(2, 2, figsize=(9, 8))
    _pairs(axs[0, 0], axs[0, 1], store, normalised=False)
    _box(axs[0, 0], store.limits.box, ec="red", lw=1.5, label="learned limits")
    _box(axs[0, 0], true_box, ec="k", ls="--", label="true learner range")
    axs[0, 0].set_xlim(TB.v)
    axs[0, 0].set_ylim(TB.w)
    axs[0, 0].set_title("teacher command domain")
    axs[0, 0].legend(fontsize=7)
    axs[0, 1].set_xlim(LB.v)
    axs[0, 1].set_ylim(LB.w)
    axs[0, 1].set_title("learner command domain")
    _pairs(axs[1, 0], axs[1, 1], store, normalised=True)
    axs[1, 0].set_title("teacher domain (normalised)")
    axs[1, 1].set_title("learner domain (normalised)")
    for a in axs.ravel():
        a.set_xlabel("v")
        a.set_ylabel("omega")
    fig.tight_layout()
    fig.savefig(out / "mpc_command_domains.png", dpi=120)
    plt.close(fig)
    files.append("mpc_command_domains.png")
    return files


def grid_figures(out: Path, store: PairStore, cmds, n: int, method, pos_err, ang_err) -> list[str]:
    box = store.limits.box
    ext = [box.v[0], box.v[1], box.w[0], box.w[1]]
    names = list(pos_err)
    headless()
    fig, axs = plt.subplots(2, len(names) + 1, figsize=(4 * (len(names) + 1), 7))
    codes = np.array([METHOD_CODES.get(m, 0) for m in method]).reshape(n, n)
    axs[0, 0].imshow(codes.T, origin="lower", extent=ext, aspect="auto", cmap="viridis", vmin=0, vmax=2)
    axs[0, 0].set_title("method (yellow: scm, green: barycentric,\nblue: perturb, purple: direct)",
                        fontsize=8)
    axs[1, 0].axis("off")
    vmax = max(float(np.percentile(pos_err["identity"], 99)), 1e-9)
    for j, k in enumerate(names):
        im = axs[0, j + 1].imshow(pos_err[k].reshape(n, n).T, origin="lower", extent=ext, aspect="auto",
                                  vmin=0, vmax=vmax)
        axs[0, j + 1].set_title(f"{k}: position error (m)")
        fig.colorbar(im, ax=axs[0, j + 1])
        im = axs[1, j + 1].imshow(ang_err[k].reshape(n, n).T, origin="lower", extent=ext, aspect="auto")
        axs[1, j + 1].set_title(f"{k}: heading error (rad)")
        fig.colorbar(im, ax=axs[1, j + 1])
    for a in axs.ravel():
        a.set_xlabel("teacher v (m/s)")
        a.set_ylabel("teacher omega (rad/s)")
    fig.tight_layout()
    fig.savefig(out / "grid_errors.png", dpi=110)
    plt.close(fig)
    return ["grid_errors.png"]


def primitives_figures(out: Path, world, scm: dict, base: dict, lib, kept, store: PairStore) -> list[str]:
    headless()
    fig, ax = plt.subplots(figsize=(10, 4.5))
    draw_mission(ax, world)
    for name, r in (("scm", scm), ("baseline", base)):
        ax.plot(r["poses"][:, 0], r["poses"][:, 1], color=COLORS[name],
                label=f"{name} ({'goal' if r['reached'] else 'no goal'}, max dev {r['max_dev_m']:.2f} m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("motion primitives: trajectories")
    fig.tight_layout()
    fig.savefig(out / "primitives_trajectories.png", dpi=120)
    plt.close(fig)

    fig, axs = plt.subplots(1, 2, figsize=(11, 4.5))
    rel = lib.relative_trajectories()
    for i in range(len(lib)):
        axs[0].plot(rel[i, :, 0], rel[i, :, 1], color="tab:blue" if kept[i] else "0.8", lw=1)
    axs[0].set_aspect("equal")
    axs[0].set_title(f"teacher primitives: {int(kept.sum())} of {len(lib)} within the learner's limits")
    c = lib.commands
    axs[1].scatter(c[~kept, 0], c[~kept, 1], c="0.8", marker="x", label="excluded")
    axs[1].scatter(c[kept, 0], c[kept, 1], c="tab:blue", s=12, label="kept")
    hull = store.limits.hull
    axs[1].fill(hull[:, 0], hull[:, 1], fill=False, ec="red", label="learner limits (calibration)")
    ids, _, T, _ = store.refined_arrays()
    Tt = store.teacher_bounds.denormalise(T)
    axs[1].scatter(Tt[:, 0], Tt[:, 1], c="k", s=8, label="calibration pairs")
    axs[1].set_xlabel("v (m/s)")
    axs[1].set_ylabel("omega (rad/s)")
    axs[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "primitives_library.png", dpi=120)
    plt.close(fig)
    return ["primitives_trajectories.png", "primitives_library.png"]
