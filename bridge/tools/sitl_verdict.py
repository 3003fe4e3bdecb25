"""Whether a run of ``scmbridge demo`` worked: its role, its figures named by that role, its corridor, and one verdict
line per claim of the method (docs/PAPER.md; the paper's Section 5.2 claims, judged on SITL against a reference made
on SITL, docs/BENCHMARKS.md "The transfer on SITL").

A run has one of three roles, by what drove the vehicle:

- ``learner``: the SC transfer (``--transfer on``): the teacher's commands mapped onto the vehicle.
- ``baseline``: the paper's baseline (``--transfer off``): the teacher's commands applied unmapped under the MPC
  bounded by the teacher's own range.
- ``reference``: the teacher on a vehicle that follows its commands (``--transfer off --limits learned`` on the
  stock rover given the learner's range): the paper's ideal teacher, made on SITL so that its deviation floor is
  SITL's own (an EKF position, a 10 Hz loop over MAVLink, the body's lag), not the simulated teacher's.

A run *reached its goal* only if it met the mission's goal rule and never left its corridor: every pose of the run
within ``corridor_m`` of the path (:func:`path_distances`, computed here from the run's own poses, apart from any
guard of the station). The claims (the issue of a vehicle never tuned for, docs/BENCHMARKS.md):

- ``goal``: the learner reached its goal without a collision, inside its corridor;
- ``time``: its time at most :data:`TIME_CLAIM` x the reference's;
- ``deviation``: its mean deviation over the last half of the path at most :data:`DEV_CLAIM` x the reference's;
- ``baseline``: its last-half deviation at most :data:`BASELINE_CLAIM` x the baseline's, or the baseline collided
  or did not reach its goal (only when both ran).
- ``assumption``: the mission inside the method's assumption for the vehicle as measured (only when the station
  checked it: a car whose turn was measured, :mod:`transfer.feasibility`): a run the station paused as
  ``outside_assumption`` is *outside the method's assumption*, its other claims failed for that reason, and
  ``scmbridge bench sitl`` counts it apart.

This module only judges and draws: the runs themselves are :mod:`bridge.tools.demo_sitl_run`'s.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

#: how far from the path a run may be at any pose and still count as following it, m (``corridor_m``)
CORRIDOR_M = 1.0
#: the learner's time may be at most this multiple of the reference's
TIME_CLAIM = 1.5
#: the learner's last-half deviation may be at most this multiple of the reference's
DEV_CLAIM = 1.5
#: ... and at most this multiple of the baseline's (unless the baseline collided or missed its goal)
BASELINE_CLAIM = 0.5
ROLES = ("reference", "learner", "baseline")
#: what each role is, in the figures' titles and the verdict lines
ROLE_TEXT = {"learner": "SC transfer", "baseline": "baseline (teacher's commands unmapped)",
             "reference": "reference (teacher on a vehicle that follows it)"}
ROLE_COLOR = {"reference": "tab:green", "learner": "tab:blue", "baseline": "tab:red"}


def role_of(transfer: str, limits: str | None) -> str:
    """The role of a run from ``--transfer`` and ``--limits`` (see the module docstring)."""
    if transfer == "on":
        return "learner"
    return "reference" if limits == "learned" else "baseline"


def path_distances(path: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """The distance of each of ``poses`` (n x 2) to the polyline ``path`` (m x 2, m >= 2): the nearest point of any
    of its segments, endpoints included."""
    P = np.asarray(poses, dtype=float).reshape(-1, 2)
    A, B = np.asarray(path[:-1], dtype=float), np.asarray(path[1:], dtype=float)
    if P.size == 0:
        return np.zeros(0)
    d = B - A  # segments
    L2 = np.maximum((d * d).sum(axis=1), 1e-18)
    t = np.clip(((P[:, None, :] - A[None]) * d[None]).sum(axis=2) / L2[None], 0.0, 1.0)
    nearest = A[None] + t[..., None] * d[None]
    return np.sqrt(((P[:, None, :] - nearest) ** 2).sum(axis=2)).min(axis=1)


def corridor(path: np.ndarray, poses: np.ndarray, corridor_m: float = CORRIDOR_M) -> dict[str, Any]:
    """``{"corridor_m", "max_path_dist_m", "left_corridor"}`` for the run's ``poses`` (every pose, from its first
    driven command to its end)."""
    dist = path_distances(path, poses)
    worst = float(dist.max()) if dist.size else 0.0
    return {"corridor_m": corridor_m, "max_path_dist_m": round(worst, 4), "left_corridor": bool(worst > corridor_m)}


def role_fields(role: str, run: dict[str, Any]) -> dict[str, Any]:
    """A run's figures under its role's names (``learner_time_s``, ``baseline_dev_last_half_m``, ...). ``run`` has
    ``reached_goal``, ``time_s`` (None when it did not reach), ``dev_last_half_m``, ``collided``, ``max_dev_m``,
    ``left_corridor``."""
    keys = ("reached_goal", "time_s", "dev_last_half_m", "collided", "max_dev_m", "left_corridor")
    return {f"{role}_{k}": run.get(k) for k in keys}


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def verdicts(fields: dict[str, Any]) -> list[dict[str, Any]]:
    """One verdict per claim from a summary's role fields (:func:`role_fields` of the runs that ran): ``claim``,
    ``ok`` (True, False, or None where it could not be judged: that run is missing) and ``line`` (what a person
    reads). The claims are about the learner (the transfer) if it ran, else about the baseline."""
    subject = "learner" if "learner_reached_goal" in fields else "baseline"
    if f"{subject}_reached_goal" not in fields:
        return []
    name = ROLE_TEXT[subject]
    reached, collided = fields[f"{subject}_reached_goal"], fields[f"{subject}_collided"]
    left, worst = fields.get(f"{subject}_left_corridor"), fields.get(f"{subject}_max_dev_m")
    goal_ok = bool(reached) and not collided and not left
    why = ("reached the goal" if reached else "did not reach the goal") + (", collided" if collided else "") + \
        (f", left its {fields.get('corridor_m', CORRIDOR_M):g} m corridor" if left else "")
    out = [{"claim": "goal", "ok": goal_ok,
            "line": f"{name}: {why}" + (f" (max {worst:.2f} m off the path)" if worst is not None else "")}]
    ref_t, ref_d = fields.get("reference_time_s"), fields.get("reference_dev_last_half_m")
    t, d = fields.get(f"{subject}_time_s"), fields.get(f"{subject}_dev_last_half_m")
    if ref_t is None:
        out.append({"claim": "time", "ok": None, "line": "not judged (no reference run that reached its goal)"})
        out.append({"claim": "deviation", "ok": None, "line": "not judged (no reference run)"})
    else:
        r = _ratio(t, ref_t)
        out.append({"claim": "time", "ok": goal_ok and r is not None and r <= TIME_CLAIM,
                    "line": (f"{t:.1f} s, {r:.2f}x the reference's {ref_t:.1f} s (claim <= {TIME_CLAIM:g}x)"
                             if r is not None else f"none (the goal was not reached; reference {ref_t:.1f} s)")
                    })
        r = _ratio(d, ref_d)
        out.append({"claim": "deviation", "ok": goal_ok and r is not None and r <= DEV_CLAIM,
                    "line": (f"{1e3 * d:.1f} mm over the last half, {r:.2f}x the reference's "
                             f"{1e3 * ref_d:.1f} mm (claim <= {DEV_CLAIM:g}x)") if r is not None
                    else "not measured (the run did not reach the path's last half)"})
    outside = fields.get("outside_assumption")
    if outside:
        out.insert(0, {"claim": "assumption", "ok": False, "line": f"{name}: stopped inside its corridor, {outside}"})
    elif fields.get("assumption_checked"):
        out.insert(0, {"claim": "assumption", "ok": True,
                       "line": f"{name}: the mission's path is inside the method's assumption for the vehicle as "
                               "measured"})
    if subject == "learner":
        if "baseline_reached_goal" not in fields:
            out.append({"claim": "baseline", "ok": None, "line": "not judged (no baseline run)"})
        else:
            b_bad = fields["baseline_collided"] or not fields["baseline_reached_goal"]
            bd = fields.get("baseline_dev_last_half_m")
            r = _ratio(d, bd)
            if b_bad:
                ok, line = goal_ok, ("the baseline " + ("collided" if fields["baseline_collided"] else
                                                         "did not reach its goal") + "; the transfer "
                                     + ("did" if goal_ok else "did not either"))
            else:
                ok = goal_ok and r is not None and r <= BASELINE_CLAIM
                line = (f"{1e3 * d:.1f} mm, {r:.2f}x the baseline's {1e3 * bd:.1f} mm (claim <= "
                        f"{BASELINE_CLAIM:g}x)") if r is not None else "not measured"
            out.append({"claim": "baseline", "ok": ok, "line": line})
    return out


def verdict_text(v: dict[str, Any]) -> str:
    """``verdict time: PASS 40.2 s, 1.10x ...`` (``n/a`` where it could not be judged; ``OUTSIDE`` for a mission
    outside the method's assumption)."""
    word = {True: "PASS", False: "FAIL", None: "n/a"}[v["ok"]]
    if v["claim"] == "assumption" and v["ok"] is False:
        word = "OUTSIDE"
    return f"verdict {v['claim']}: {word} {v['line']}"


def worked(vs: list[dict[str, Any]]) -> bool | None:
    """Whether every claim that could be judged held (None if none could be)."""
    judged = [v["ok"] for v in vs if v["ok"] is not None]
    return all(judged) if judged else None


def into_frame(traj: np.ndarray, pose_from: tuple[float, float, float],
               pose_to: tuple[float, float, float]) -> np.ndarray:
    """A trajectory of a run whose mission was placed at ``pose_from`` moved rigidly into the frame of a run whose
    mission was placed at ``pose_to`` (each SITL boot places the mission where the vehicle stands)."""
    (fx, fy, fth), (tx, ty, tth) = pose_from, pose_to
    c, s = math.cos(tth - fth), math.sin(tth - fth)
    T = np.asarray(traj, dtype=float).copy()
    if T.size == 0:
        return T
    dx, dy = T[:, 0] - fx, T[:, 1] - fy
    T[:, 0], T[:, 1] = tx + c * dx - s * dy, ty + s * dx + c * dy
    return T


def title(role: str, model: str) -> str:
    """A figure's title by what ran."""
    return f"ArduPilot SITL {model}: {ROLE_TEXT[role]}"


def run_figure(path: Path, world, traj: np.ndarray, role: str, model: str) -> None:
    """One run's trajectory over the mission, titled by what ran."""
    compare_figure(path, world, {role: traj}, model)


def compare_figure(path: Path, world, trajs: dict[str, np.ndarray], model: str) -> None:
    """The runs' trajectories (by role: reference, transfer, baseline) over the one mission, each in its colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim_learner.figures import draw_mission

    fig, ax = plt.subplots(figsize=(9, 4))
    draw_mission(ax, world)
    for role in ROLES:
        traj = trajs.get(role)
        if traj is not None and len(traj):
            ax.plot(traj[:, 0], traj[:, 1], color=ROLE_COLOR[role], lw=1.2, label=ROLE_TEXT[role])
    ax.legend(loc="upper right", fontsize=7)
    ax.set_title(f"ArduPilot SITL {model}: " + ", ".join(ROLE_TEXT[r].split(" (")[0] for r in ROLES if r in trajs))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
