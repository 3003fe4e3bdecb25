"""sim_learner/figures.py: the simulations' figures like the paper's, written as PNG files.

The simulations write them end to end in tests/unit/sim_learner/test_experiments.py (``--out``); here each
function on small inputs: the files it says it wrote are there, are PNG images of the size asked for, and its
helpers draw what they name."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Circle

from sim_learner.figures import METHOD_CODES, draw_mission, grid_figures, mpc_figures, primitives_figures
from sim_learner.runs import Run
from sim_learner.worlds import mpc_world
from tests.boxes import LB, TB
from transfer.domain import Bounds
from transfer.store import PairStore
from transfer.teacher.primitives import PrimitiveLibrary


def _store() -> PairStore:
    s = PairStore(LB, TB, k_min=1)
    for n in ([0.1, 0.1], [0.9, 0.1], [0.5, 0.9], [0.5, 0.5], [1.0, 0.5]):
        u = LB.denormalise(n)
        s.add(u * np.array([1.5, 1.2]), u)
    return s


def _png(path: Path) -> tuple[int, int]:
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    h, w = mpimg.imread(path).shape[:2]
    return w, h


def test_draw_mission_draws_the_path_the_obstacles_and_the_goal() -> None:
    world = mpc_world(0.5)
    fig, ax = plt.subplots()
    draw_mission(ax, world)
    circles = [p for p in ax.patches if isinstance(p, Circle)]
    assert len(circles) == len(world.obstacles)
    assert sorted(c.radius for c in circles) == sorted(world.obstacles[:, 2])
    path, goal = ax.lines
    np.testing.assert_allclose(path.get_xydata(), world.path.points)
    assert path.get_label() == "desired path" and goal.get_xydata().tolist() == [list(world.goal)]
    assert ax.get_aspect() == 1.0


def test_mpc_figures_writes_its_three_files(tmp_path: Path) -> None:
    world = mpc_world(0.5)
    runs = []
    for name, dy in (("teacher", 0.0), ("scm", 0.1), ("baseline", 0.4)):
        r = Run(name, poses=[np.r_[p + [0.0, dy], 0.0] for p in world.path.points[::20]], reached=name != "baseline")
        runs.append(r)
    files = mpc_figures(tmp_path, world, runs, _store(), LB, TB, LB)
    assert files == ["mpc_trajectories.png", "mpc_deviation.png", "mpc_command_domains.png"]
    assert _png(tmp_path / files[0]) == (9 * 120, 4 * 120)
    assert _png(tmp_path / files[1]) == (7 * 120, int(3.5 * 120))
    assert _png(tmp_path / files[2]) == (9 * 120, 8 * 120)


def test_grid_figures_writes_the_error_maps(tmp_path: Path) -> None:
    n = 4
    method = ["scm", "direct", "perturb", "barycentric", "affine"] * 3 + ["scm"]
    rng = np.random.default_rng(0)
    pos = {"identity": rng.random(n * n), "scm": 0.1 * rng.random(n * n)}
    ang = {"identity": rng.random(n * n), "scm": 0.1 * rng.random(n * n)}
    files = grid_figures(tmp_path, _store(), None, n, method, pos, ang)
    assert files == ["grid_errors.png"]
    assert _png(tmp_path / "grid_errors.png") == (4 * 3 * 110, 7 * 110)  # one column per map, and the methods'
    assert METHOD_CODES == {"direct": 0, "perturb": 1, "barycentric": 1.5, "scm": 2}


def test_primitives_figures_writes_the_trajectories_and_the_library(tmp_path: Path) -> None:
    tb = Bounds((0.0, 3.0), (-math.pi / 3, math.pi / 3))
    lib = PrimitiveLibrary(tb, 5)
    kept = lib.commands[:, 0] <= 1.5
    poses = np.c_[np.linspace(0, 8, 30), np.zeros(30), np.zeros(30)]
    scm = {"poses": poses, "reached": True, "max_dev_m": 0.1}
    base = {"poses": poses + [0.0, 0.5, 0.0], "reached": False, "max_dev_m": 0.6}
    s = PairStore(LB, tb, k_min=1)
    for n in ([0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]):
        s.add(tb.denormalise(np.array(n) * 0.5), LB.denormalise(n))
    files = primitives_figures(tmp_path, mpc_world(), scm, base, lib, kept, s)
    assert files == ["primitives_trajectories.png", "primitives_library.png"]
    assert _png(tmp_path / files[0]) == (10 * 120, int(4.5 * 120))
    assert _png(tmp_path / files[1]) == (11 * 120, int(4.5 * 120))
