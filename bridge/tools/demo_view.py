"""The demo's trajectory figure, coloured by how each command was obtained (README.md, "Glossary").

Each pose of the learner is drawn in the colour of the method of the command the vehicle was executing when it was
measured: the last command the driver host echoed as driven (``Applied`` reason ``cmd`` or ``clamped``, one clock with
the poses) and the method the station named in that ``Command``. So a newcomer sees where the SC map drove the robot
(``scm``), where linear interpolation did (``barycentric``), and where the policy applied or explored commands.
"""

from __future__ import annotations

from bisect import bisect_right
from collections import Counter
from pathlib import Path

import numpy as np

#: a colour per method the README names (README.md, "Glossary"); any other method is drawn grey
METHOD_COLORS = {"scm": "tab:blue", "barycentric": "tab:green", "direct": "tab:orange", "perturb": "tab:red",
                 "calibrate": "tab:purple", "affine": "tab:brown", "stop": "0.55"}
#: what each method means, for the legend
METHOD_MEANING = {"scm": "SC map of a mapping region", "barycentric": "linear interpolation of pairs",
                  "direct": "teacher command applied directly", "perturb": "exploring an empty cell",
                  "calibrate": "calibration grid", "affine": "affine fit of all pairs", "stop": "stopped / parked"}


def methods_along(states: list[tuple[float, float, float, float]], applied: list[tuple[float, str, int | None]],
                  cmds: dict[int, str]) -> list[str]:
    """The method of the command driving at each pose ``(stamp, x, y, theta)``: the latest driven echo at or before
    the pose's stamp, that command's method (``stop`` before the first one, after a stop, or for a command whose
    ``Command`` this process did not see)."""
    driven = sorted((a[0], a[2]) for a in applied if a[1] in ("cmd", "clamped") and a[2] is not None)
    others = sorted(a[0] for a in applied if a[1] not in ("cmd", "clamped"))
    stamps = [d[0] for d in driven]
    out = []
    for s in states:
        k = bisect_right(stamps, s[0]) - 1
        if k < 0:
            out.append("stop")
            continue
        j = bisect_right(others, s[0]) - 1  # a later non-driving echo (a stop, a hold) ends that command
        out.append("stop" if j >= 0 and others[j] > stamps[k] else cmds.get(int(driven[k][1]), "stop"))
    return out


def trajectory_figure(out: Path, world, traj: np.ndarray, methods: list[str], label: str,
                      title: str = "HIL demo: SCM transfer of the teacher MPC") -> Path:
    """``demo_trajectory.png`` in ``out``: the mission and the learner's path, each segment in its method's colour,
    the legend giving each method's share of the poses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    from sim_learner.figures import draw_mission

    fig, ax = plt.subplots(figsize=(9, 5.2))
    draw_mission(ax, world)
    xy = np.asarray(traj, dtype=float)[:, :2]
    if len(xy) >= 2 and len(methods) == len(xy):
        segs = np.stack([xy[:-1], xy[1:]], axis=1)
        colours = [METHOD_COLORS.get(m, "0.3") for m in methods[1:]]
        ax.add_collection(LineCollection(segs, colors=colours, linewidths=2.2, zorder=3))
        counts = Counter(methods[1:])
        for m, n in sorted(counts.items(), key=lambda e: -e[1]):
            ax.plot([], [], color=METHOD_COLORS.get(m, "0.3"), lw=2.2,
                    label=f"{m}: {METHOD_MEANING.get(m, 'other')} ({100 * n / len(segs):.0f} %)")
    elif len(xy):
        ax.plot(xy[:, 0], xy[:, 1], color="tab:blue", lw=1.5)
    ax.plot([], [], " ", label=f"learner over Zenoh + {label}; colour: how its command was mapped")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=7)  # below: no obstacle hidden
    ax.set_title(title)
    fig.tight_layout()
    path = out / "demo_trajectory.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
