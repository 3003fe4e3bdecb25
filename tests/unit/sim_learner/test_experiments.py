"""Shortened paper simulations (``scmbridge sim ... --quick``), judged on a seed sweep.

The closed loop (MPC + exploration + refinement) amplifies floating-point differences: on another CPU the same
seed follows another trajectory. So every MPC figure is judged on the median of a sweep over ``SEEDS``, in which
each seed also moves the learner's start by up to 1 mm / 1 mrad (sampling exactly that sensitivity), against a
threshold with a margin far above the sweep's spread, and never by exact equality. The margins are stated next to
each assertion (measured here, 10 seeds); the thresholds still fail the identity mapper or an affine map where the
test says so. (The paper's exploration policy now passes the time, deviation and perturbation thresholds too, with
less margin: the transfer step keeps it, as the guided one, from exploring next to obstacles.) Claims that do not
hold are not tested as xfails: docs/PAPER.md states them with the sweep's numbers.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from bridge.nodes.station_tags import read_store
from bridge.tools.cli import main
from sim_learner.experiments import grid_experiment, mpc_case, run_scm, scm_figures

SEEDS = (0, 1, 2, 3, 4)

#: pytest-timeout's bound for every test here: in-process computation and the sweep's two worker processes (the sweep
#: fixture is set up within its first test's bound), so the bound is a guard against a hang, not a speed check. The
#: default 120 s was one: a machine running six test workers beside two busy loops gives each a fraction of a core, and
#: after such a cut the module's later tests failed too.
HANG_S = 400
pytestmark = pytest.mark.timeout(HANG_S)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> dict:
    """``scmbridge sim mpc --quick --seeds 0-4 --policy guided`` (two worker processes): its JSON, the pair stores
    it wrote, and the output directory."""
    out = tmp_path_factory.mktemp("sweep")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["sim", "mpc", "--quick", "--seeds", "0-4", "--policy", "guided", "--workers", "2",
                     "--out", str(out)]) == 0
    summary = json.loads(buf.getvalue())
    assert json.loads((out / "mpc_sweep.json").read_text())["policies"] == summary["policies"]
    stores = {s: read_store(out / f"pairs-guided-{s}.bin") for s in SEEDS}
    return {"summary": summary, "stats": summary["policies"]["guided"]["stats"],
            "per_seed": summary["policies"]["guided"]["per_seed"], "stores": stores, "out": out}


def test_sweep_json_is_plain_data_with_median_spread_and_worst_seed(sweep) -> None:
    s = sweep["summary"]
    assert s["seeds"] == list(SEEDS) and [p["seed"] for p in sweep["per_seed"]] == list(SEEDS)
    for fig in ("scm_time_ratio", "scm_dev_ratio", "perturb_share", "limits_rel_err"):
        st = sweep["stats"][fig]
        assert st["min"] <= st["median"] <= st["max"] and st["worst_seed"] in SEEDS
    refs = s["references"]
    assert set(refs["baselines"]) == {"teacher_range", "true_range"}
    for b in refs["baselines"].values():
        assert {"time_s", "reached_goal", "dev_last_half_m", "collided", "time_ratio", "dev_ratio"} <= set(b)


def test_mpc_scm_learner_reaches_the_goal_safely_and_learns_its_limits(sweep) -> None:
    # every seed (not the median): goal, no collision, limits within 10 % (measured <= 5e-7: margin 2e5x)
    assert sweep["stats"]["no_goal_seeds"] == [] and sweep["stats"]["collided_seeds"] == []
    assert not sweep["summary"]["references"]["teacher"]["collided"]
    assert sweep["stats"]["limits_rel_err"]["max"] <= 0.10
    for s in sweep["per_seed"]:
        c = s["method_counts"]
        assert c["scm"] + c.get("barycentric", 0) + c["direct"] > c["perturb"]


def test_mpc_scm_learner_is_within_1_2x_the_ideal_teacher_time(sweep) -> None:
    # the paper: shortly after the ideal teacher; the goal 1.2x (the paper's own bound in the tests was
    # 1.25x). Measured median 1.06 (max 1.07 over 10 seeds): margin 0.14. The paper's exploration policy: median
    # 1.10 (seeds 0-9; 1.21 while it still explored next to obstacles).
    assert sweep["stats"]["scm_time_ratio"]["median"] <= 1.2


def test_mpc_scm_deviation_last_half_within_1_5x_teacher(sweep) -> None:
    # measured median 0.70 (max 0.99 over 10 seeds): margin 0.8. The paper's policy: median 1.01 (10 seeds).
    assert sweep["stats"]["scm_dev_ratio"]["median"] <= 1.5


def test_mpc_exploration_costs_at_most_15_percent_of_the_commands(sweep) -> None:
    # measured median 3.9 % (max 4.2 %): margin 11 points. The paper's policy: median 11 % (seeds 0-9, worst
    # 21 %; 19 % while it still explored next to obstacles).
    assert sweep["stats"]["perturb_share"]["median"] <= 0.15


def test_mpc_baselines_reach_the_goal_and_the_papers_baseline_tracks_worse(sweep) -> None:
    # The paper's >= 2x slowdown of the baseline is not reproduced (docs/PAPER.md): both baselines finish in about the
    # ideal teacher's time (0.97x, 0.98x). What holds: both reach the goal without collision, and the paper's
    # baseline (MPC bounded by the teacher's own range) deviates >= 1.5x the teacher over the last half
    # (measured 2.2x; deterministic, no exploration) while the SCM learner stays within 1.5x (above).
    b = sweep["summary"]["references"]["baselines"]
    for base in b.values():
        assert base["reached_goal"] and not base["collided"]
    assert b["teacher_range"]["dev_ratio"] >= 1.5


def test_mpc_seed_is_deterministic_across_processes(sweep) -> None:
    # the same seed in this process reproduces the worker's run bit for bit (the same machine)
    run, store = run_scm(SEEDS[0], True, "guided")
    assert scm_figures(run, store, True)["commands_digest"] == sweep["per_seed"][0]["commands_digest"]


@pytest.mark.parametrize("solver", ["rti-qpoases", "rti-daqp"])
def test_a_real_time_iteration_run_does_not_depend_on_the_runs_before_it_in_its_process(solver: str) -> None:
    # the QP solvers' working sets outlive a reset: each run gets solvers of its own, so a seed run again after
    # another seed is the same run, bit for bit (a sweep's worker meets its seeds in any order)
    first, store = run_scm(1, True, "guided", solver=solver)
    run_scm(0, True, "guided", solver=solver)
    again, store_again = run_scm(1, True, "guided", solver=solver)
    assert np.array_equal(np.asarray(first.commands), np.asarray(again.commands))
    digests = [scm_figures(r, st, True)["commands_digest"] for r, st in ((first, store), (again, store_again))]
    assert digests[0] == digests[1]


def test_grid_scm_region_error_beats_the_baseline_and_an_affine_map(sweep) -> None:
    # the exhaustive 0.1 s test on the pairs each seed learned. Measured (guided pairs, with the guided policy's
    # fills): SCM / baseline median position error 0.13-0.16 (median 0.15) on these seeds, 0.13-0.27 over 0-9;
    # threshold 0.25 (before the fills: 0.25-0.30, median 0.29, which fails it). The full-size claim is docs/PAPER.md's.
    ratios, affine = [], []
    for s in SEEDS:
        g = grid_experiment(seed=s, quick=True, out=None, progress=False, store=sweep["stores"][s])
        assert g["scm_region_fraction"] > 0.5
        base = g["baseline_median_pos_err_m"]
        ratios.append(g["scm_region_median_pos_err_m"] / base)
        affine.append(g["mappers"]["affine"]["region_median_pos_err_m"] / base)
    assert float(np.median(ratios)) <= 0.25 and float(np.median(ratios)) < float(np.median(affine))


def test_cli_grid_on_a_saved_store_writes_json_figures_and_trajectories(sweep, tmp_path, capsys) -> None:
    store = sweep["out"] / "pairs-guided-0.bin"
    assert main(["sim", "grid", "--quick", "--store", str(store), "--out", str(tmp_path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["experiment"] == "grid" and "scm_region_median_pos_err_m" in out
    assert (tmp_path / "grid_errors.png").stat().st_size > 10_000
    # the transfer's own errors beside each mapper's: what the station runs (the SC map or the line, per command)
    mine = out["mappers"]["transfer"]
    assert mine["region_median_pos_err_m"] > 0 and mine["region_p95_pos_err_m"] >= mine["region_median_pos_err_m"]
    region = np.asarray(np.load(tmp_path / "grid.npz")["method"]) == "scm"
    with np.load(tmp_path / "grid.npz") as z:
        assert z["pos_err_transfer"].shape == z["ang_err_transfer"].shape == z["pos_err_scm"].shape
        assert float(np.median(z["pos_err_transfer"][region])) == mine["region_median_pos_err_m"]
        assert set(z["method_transfer"][region]) <= {"scm", "barycentric"}
    assert sum(out["transfer_methods_region"].values()) == int(region.sum())


def test_cli_grid_over_seeds_runs_each_seeds_mpc_and_summarises(capsys) -> None:
    assert main(["sim", "grid", "--quick", "--seeds", "0", "--workers", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["experiment"] == "grid-sweep" and out["seeds"] == [0] and out["exploration"] == "guided"
    (one,) = out["per_seed"]
    assert out["stats"]["scm_to_baseline"]["median"] == one["scm_to_baseline"] < 1.0
    assert one["scm_to_baseline_all"] > 0 and one["refined_pairs"] >= 3
    assert one["transfer_to_barycentric_median"] > 0 and one["transfer_to_scm_p95"] > 0
    assert main(["sim", "grid", "--quick", "--seeds", "0", "--store", "x.bin"]) == 2
    assert "exclude each other" in capsys.readouterr().err


def test_primitives_scm_learner_reaches_the_goal_and_the_baseline_deviates_3x_more() -> None:
    from sim_learner.primitives_sim import run_primitives

    s = run_primitives(seed=0, quick=True, out=None, progress=False)
    # the kept primitives are those inside the learner's true limits (the calibration learns the per-axis scaled
    # box to 1e-12): all of them well inside are kept, none well outside; the library's grid points exactly on
    # the limits make the paper's 35 (5 speeds x 7 turn rates), with 30 if a float puts them outside
    assert 30 <= s["kept_primitives"] <= 35
    lo, hi = np.array(s["learned_limits"])[[0, 2]], np.array(s["learned_limits"])[[1, 3]]
    true_hi = np.array([1.2 * 1.0, 1.6 * np.pi / 8])
    np.testing.assert_allclose([hi[0], hi[1], -lo[1]], [true_hi[0], true_hi[1], true_hi[1]], rtol=1e-6)
    # measured 4.2-4.4x over seeds 0-3 (noise differs per seed): margin 1.2x
    assert s["scm_reached_goal"] and not s["scm_collisions"]
    assert (not s["baseline_reached_goal"]) or s["baseline_collisions"] or (
        s["baseline_max_dev_m"] >= 3 * s["scm_max_dev_m"])


def test_the_quick_case_is_the_papers_mpc_case_scaled() -> None:
    case = mpc_case(True)
    assert case.true_box.as_list() == pytest.approx([0.05, 0.3, -np.pi / 16, np.pi / 12])
    assert case.teacher_bounds.as_list() == pytest.approx([0.05, 0.6, -np.pi / 4, np.pi / 4])


def test_the_mpc_case_runs_with_the_stations_change_detection_and_says_so(tmp_path, capsys) -> None:
    """``sim mpc --adapt``: the same case with the store a station runs under ``[transfer] adapt``, on this learner
    that does not change (what it costs there: docs/PAPER.md, 'a learner that changes'); the saved store is one
    with change detection, and nothing in this unchanged run is re-learned."""
    assert main(["sim", "mpc", "--quick", "--seeds", "0", "--policy", "guided", "--workers", "1", "--adapt",
                 "--out", str(tmp_path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["adapt"] is True and summary["policies"]["guided"]["stats"]["no_goal_seeds"] == []
    assert summary["policies"]["guided"]["stats"]["collided_seeds"] == []
    store = read_store(tmp_path / "pairs-guided-0.bin")
    assert store.adapt and store.relearned == 0
