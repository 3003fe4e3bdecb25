"""What the paper's simulations share: the control interval, a progress bar, the teacher's MPC of a run, one
closed-loop run and its deviation.

Both :mod:`sim_learner.experiments` (the MPC case, the grid test, the seed sweep) and
:mod:`sim_learner.primitives_sim` (the motion-primitive case) import from here; neither imports the other.
"""

from __future__ import annotations

import functools
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from sim_learner.worlds import World

if TYPE_CHECKING:
    from transfer.teacher.mpc import MpcTeacher

DT = 0.1  # s, the control interval of every simulation (and the pairing interval)


@functools.lru_cache(maxsize=4)
def _mpc_build(solver: str, curve_margin: float) -> tuple[MpcTeacher, list | None]:
    """One MPC per process, solver and ``curve_margin``, and the compiled code of its real-time iteration where the
    machine can build it (:mod:`bridge.teacher.codegen`; None for IPOPT or without a compiler)."""
    from bridge.teacher.codegen import build_mpc, compile_functions
    from transfer.teacher.mpc import MpcConfig

    mpc = build_mpc(MpcConfig(N=20, dt=DT, solver=solver, curve_margin=curve_margin))
    compiled = compile_functions(mpc.kernels()) if solver != "ipopt" else None
    if compiled is not None:
        mpc.use_compiled(compiled)
    return mpc, compiled


def mpc_teacher(solver: str = "ipopt", curve_margin: float = 0.0) -> MpcTeacher:
    """The MPC of one run. IPOPT's is the process's one (``reset`` before every run clears its warm start). The
    real-time iteration's QP solvers keep their working sets from solve to solve, and a working set, though only a
    starting guess, moves a solution in its last bits, which a closed loop carries on: each run gets solvers of its own
    (sharing the process's build and compiled code), so that a run does not depend on the runs the
    process made before it."""
    mpc, compiled = _mpc_build(solver, curve_margin)
    if solver == "ipopt":
        return mpc
    from bridge.teacher.codegen import build_mpc

    fresh = build_mpc(mpc.cfg)
    if compiled is not None:
        fresh.use_compiled(compiled)
    return fresh


class Progress:
    """A one-line progress bar on stderr when it is a terminal; silent otherwise."""

    def __init__(self, label: str) -> None:
        self.label = label
        self.tty = sys.stderr.isatty()

    def __call__(self, frac: float, text: str = "") -> None:
        if self.tty:
            n = int(30 * min(max(frac, 0.0), 1.0))
            sys.stderr.write(f"\r{self.label:>10} [{'#' * n}{'.' * (30 - n)}] {100 * frac:5.1f}% {text:<30}")
            sys.stderr.flush()

    def done(self) -> None:
        if self.tty:
            sys.stderr.write("\n")


@dataclass
class Run:
    """One closed-loop run: poses, commands sent, the teacher's commands, methods, whether and when it reached
    the goal."""

    name: str
    poses: list[NDArray[np.float64]] = field(default_factory=list)
    commands: list[NDArray[np.float64]] = field(default_factory=list)
    teacher_cmds: list[NDArray[np.float64]] = field(default_factory=list)
    methods: list[str] = field(default_factory=list)
    regions: list[tuple[int, ...]] = field(default_factory=list)  # refined-pair ids behind each command, if any
    reached: bool = False
    collided: bool = False
    time_s: float | None = None
    solve_s: list[float] = field(default_factory=list)
    failures: int = 0

    def arrays(self) -> dict[str, NDArray]:
        """The run as named arrays for an ``.npz`` file."""
        return {
            f"{self.name}_poses": np.array(self.poses),
            f"{self.name}_commands": np.array(self.commands).reshape(-1, 2),
            f"{self.name}_teacher": np.array(self.teacher_cmds).reshape(-1, 2),
        }

    def method_counts(self) -> dict[str, int]:
        """How many commands each method produced (every method that occurred, plus scm/direct/perturb)."""
        counts = {m: 0 for m in ("scm", "direct", "perturb")}
        for m in self.methods:
            counts[m] = counts.get(m, 0) + 1
        return counts


def deviation_profile(poses: list[NDArray[np.float64]] | NDArray[np.float64],
                      world: World) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(progress along the path in [0, 1], distance to the path in m) for every pose."""
    prog, dev = [], []
    for p in poses:
        s, d = world.path.project(np.asarray(p, dtype=float)[:2])
        prog.append(s / world.path.length)
        dev.append(d)
    return np.array(prog), np.array(dev)


def mean_dev_last_half(run: Run, world: World) -> float | None:
    """Mean distance to the path over the poses in the second half of the path (by progress); None if the run
    never got there. The paper's deviation claim is judged on this: the first half holds the misaligned start."""
    prog, dev = deviation_profile(run.poses, world)
    m = prog >= 0.5
    return float(dev[m].mean()) if m.any() else None
