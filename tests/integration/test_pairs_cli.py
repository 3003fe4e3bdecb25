"""``scmbridge pairs show|plot``: what was learned, from a store file offline and from a running station over Zenoh
(a real ``scmbridge station`` process on a free 127.0.0.1 port), and one line with exit status 2 when no station
answers. Every process started here is stopped; every test is bounded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bridge.core.paths import save_atomic
from bridge.nodes.station_core import pairs_message
from bridge.nodes.zsession import free_port, tcp
from bridge.tools.cli import main as cli_main
from bridge.tools.pairs_cli import from_message, from_store, pairs_figure
from bridge.tools.procs import spawn, stop_group
from sim_learner.dynamics import MPC_TEACHER_V, MPC_TEACHER_W, mpc_learner
from transfer.domain import Bounds
from transfer.mappers import BarycentricMapper
from transfer.pairs import teacher_equivalent
from transfer.store import PairStore

ROOT = Path(__file__).resolve().parents[2]
PNG = b"\x89PNG\r\n\x1a\n"


def cubic_store(seed: int = 0, visits: int = 5) -> PairStore:
    """Refined pairs of the paper's cubic learner, learned the way ``scmbridge demo --inprocess`` does: noisy
    visits of every learner cell (k_min = 5), then the learner's extremes for its limits on the teacher domain."""
    rng = np.random.default_rng(seed)
    learner = mpc_learner()
    LB = Bounds(learner.v_range, learner.w_range)
    store = PairStore(LB, Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=5)
    x0, dt = np.zeros(3), 0.1
    g = (np.arange(11) + 0.5) / 11
    for _ in range(visits):
        for a in g:
            for b in g:
                u = LB.clip(LB.denormalise([a, b] + 0.02 * rng.standard_normal(2)))
                store.add(teacher_equivalent(x0, learner.step(x0, u, dt), dt), u)
    for u in LB.corners():
        store.add(teacher_equivalent(x0, learner.step(x0, u, dt), dt), u)
    return store


@pytest.fixture(scope="module")
def store() -> PairStore:
    return cubic_store()


@pytest.fixture()
def store_file(store: PairStore, tmp_path: Path) -> Path:
    f = tmp_path / "pairs.bin"
    save_atomic(f, store.to_bytes())
    return f


def _same_as_store(out: dict, store: PairStore) -> None:
    """The JSON view holds exactly the store's refined pairs and learned limits."""
    refined = store.refined()
    assert [p["id"] for p in out["pairs"]] == [p.id for p in refined]
    assert [p["count"] for p in out["pairs"]] == [p.count for p in refined]
    assert [p["version"] for p in out["pairs"]] == [p.version for p in refined]
    np.testing.assert_allclose([p["teacher"] for p in out["pairs"]], [p.u_T for p in refined], rtol=0, atol=1e-12)
    np.testing.assert_allclose([p["learner"] for p in out["pairs"]], [p.u_L for p in refined], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["limits"]["box"], store.limits.box.as_list(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(out["limits"]["hull"], store.limits.hull, rtol=0, atol=1e-12)
    assert out["cells"] == {"configured": len(refined), "total": 121, "grid": [11, 11]}
    assert out["teacher_bounds"] == store.teacher_bounds.as_list()
    assert out["learner_bounds"] == store.learner_bounds.as_list()


def test_show_json_from_a_store_file(store: PairStore, store_file: Path, capsys) -> None:
    assert cli_main(["pairs", "show", "--store", str(store_file), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    _same_as_store(out, store)
    assert 80 <= len(out["pairs"]) <= 121 and out["raw_pairs"] == store.raw_count and out["k_min"] == 5
    assert out["latest_command"] is None and out["warnings"] == []
    # the learned limits are the cubic learner's range on the teacher domain (its extremes were driven)
    np.testing.assert_allclose(out["limits"]["box"], store.learner_bounds.as_list(), atol=5e-3)
    assert cli_main(["pairs", "show", "--store", str(store_file)]) == 0
    text = capsys.readouterr().out
    assert f"configured cells: {len(out['pairs'])} of 121" in text and "learned limits on the teacher domain" in text


def test_plot_from_a_store_file_and_the_demos_figure(store: PairStore, store_file: Path, tmp_path: Path,
                                                     capsys) -> None:
    png = tmp_path / "figs" / "pairs.png"
    assert cli_main(["pairs", "plot", "--store", str(store_file), "--out", str(png)]) == 0
    assert png.read_bytes().startswith(PNG) and png.stat().st_size > 10_000
    ids = [p.id for p in store.refined()][:4]
    assert pairs_figure(store_file, tmp_path / "demo.png", region=ids).stat().st_size > 10_000
    empty = tmp_path / "empty.bin"  # a station that has learned nothing yet still gets a figure
    save_atomic(empty, PairStore(store.learner_bounds, store.teacher_bounds).to_bytes())
    assert pairs_figure(empty, tmp_path / "empty.png").stat().st_size > 10_000


def test_the_triangulation_drawn_is_the_mappers_and_regions_are_its_triangles(store: PairStore) -> None:
    """A view built from the station's Pairs reply (teacher units, the bounds from the configuration) triangulates
    exactly as the station's mappers do, so the region ids of a command are a triangle of what is drawn."""
    view = from_message(pairs_message(store, "r", 1.0), store.teacher_bounds, store.learner_bounds, store.grid,
                        "test", "test")
    assert view.warnings == []
    tris = {frozenset(int(view.ids[k]) for k in t) for t in view.triangles()}
    assert tris == {frozenset(int(view.ids[k]) for k in t) for t in from_store(store, "s").triangles()}
    mapper = BarycentricMapper(store)
    rng = np.random.default_rng(1)
    box = store.limits.box
    hits = 0
    for _ in range(20):
        uT = box.denormalise(0.1 + 0.8 * rng.random(2))
        res = mapper.map_normalised(store.teacher_bounds.normalise(uT))
        if res is not None:
            hits += 1
            assert frozenset(res[1]) in tris
    assert hits >= 10
    # a station run with another grid or other bounds is named, not drawn silently wrong
    other = from_message(pairs_message(store, "r", 1.0), store.teacher_bounds, Bounds((0.1, 0.2), (-0.1, 0.1)),
                         (5, 5), "config other.toml", "test")
    assert len(other.warnings) == 2 and all("other.toml" in w for w in other.warnings)


def test_a_store_that_cannot_be_read_is_one_line(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"not a store")
    for f in (bad, tmp_path / "missing.bin"):
        assert cli_main(["pairs", "show", "--store", str(f)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("scmbridge pairs show: error: ") and str(f) in err


def _cli(*args: str, timeout: float = 90) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", "pairs", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def test_a_running_station_answers_with_what_its_store_holds(store: PairStore, store_file: Path,
                                                             tmp_path: Path) -> None:
    port, robot = free_port(), f"pairs{os.getpid()}"
    with open(tmp_path / "station.log", "w") as log:
        proc = spawn(["station", "--start", "--robot", robot, "--listen", tcp(port), "--store", str(store_file),
                      "--duration", "90"], log, cwd=ROOT)
        try:
            # the query is retried until --timeout: it covers the station's start (imports, SC kernel warm-up)
            res = _cli("show", "--robot", robot, "--connect", tcp(port), "--json", "--timeout", "60")
            assert res.returncode == 0, res.stderr + (tmp_path / "station.log").read_text()[-2000:]
            out = json.loads(res.stdout)
            png = tmp_path / "live.png"
            res_plot = _cli("plot", "--robot", robot, "--connect", tcp(port), "--out", str(png), "--timeout", "30")
        finally:
            stop_group(proc)
    _same_as_store(out, store)
    assert out["robot"] == robot and out["raw_pairs"] is None and out["warnings"] == []
    # no driver host: the station publishes stops (no region), and the cmd subscription saw one
    assert out["latest_command"] is not None and out["latest_command"]["method"] == "stop"
    assert out["latest_command"]["region"] == []
    assert res_plot.returncode == 0, res_plot.stderr
    assert png.read_bytes().startswith(PNG) and png.stat().st_size > 10_000


def test_no_station_is_one_line_and_exit_status_2() -> None:
    port = free_port()  # nothing listens there
    res = _cli("show", "--robot", "ghost", "--connect", tcp(port), "--timeout", "1", timeout=30)
    assert res.returncode == 2 and res.stdout == ""
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert "no station answered" in lines[0] and "'ghost'" in lines[0] and tcp(port) in lines[0]
    res = _cli("plot", "--robot", "ghost", "--mode", "client", "--connect", tcp(port), "--timeout", "1",
               "--out", "never.png", timeout=30)
    assert res.returncode == 2 and len(res.stderr.splitlines()) == 1 and tcp(port) in res.stderr
    assert not (ROOT / "never.png").exists()


def test_show_names_the_cells_whose_learner_changed_and_when(tmp_path: Path, capsys) -> None:
    """A store with change detection (``[transfer] adapt``) whose learner changed in the top-speed row (a dragging
    wheel: 15 % of the yaw-rate range) names those cells, how often and when (the station's wall-clock stamps), from
    the file and through the station's ``Pairs`` reply on the wire."""
    from bridge.core import wire as M

    learner = mpc_learner()
    lb = Bounds(learner.v_range, learner.w_range)
    st = PairStore(lb, Bounds(MPC_TEACHER_V, MPC_TEACHER_W), k_min=5, adapt=True)
    rng = np.random.default_rng(2)
    wall = 1_795_000_000.0  # 2026-11-18 UTC
    bias = np.array([0.0, 0.15 * (lb.w[1] - lb.w[0])])
    for k, shift in enumerate((np.zeros(2), bias)):
        for _ in range(10 if k == 0 else 8):
            for i in range(11):
                for j in range(11):
                    if k and i != 10:  # today only the top-speed row is driven
                        continue
                    u = lb.denormalise((np.array([i, j]) + rng.uniform(0.1, 0.9, 2)) / 11)
                    st.add(learner.response(u) + shift, u, stamp=wall + k * 3600.0)
    changed = st.changed_cells()
    assert [c.id for c in sorted(changed, key=lambda c: c.id)] == [110 + j for j in range(11)]
    assert all(c.count == 1 and c.at == wall + 3600.0 for c in changed)
    f = tmp_path / "pairs.bin"
    save_atomic(f, st.to_bytes())
    assert cli_main(["pairs", "show", "--store", str(f), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert sorted(c["id"] for c in out["changed_cells"]) == [110 + j for j in range(11)]
    assert all(c["count"] == 1 and c["at"] == wall + 3600.0 for c in out["changed_cells"])
    assert cli_main(["pairs", "show", "--store", str(f)]) == 0
    text = capsys.readouterr().out
    assert "changed cells (their learner no longer answered as their pairs said; re-learned): 11" in text
    assert "cell  115 (v 10, omega 5 on the grid): re-learned 1x, last 2026-11-18 12:06:40 UTC" in text
    # the station's reply carries them (an optional field: absent, so not sent, while no cell changed)
    msg = M.decode(M.encode(pairs_message(st, "r", 1.0)), M.Pairs)
    view = from_message(msg, st.teacher_bounds, st.learner_bounds, st.grid, "test", "test")
    assert view.changed == [(c.id, c.count, c.at) for c in changed]
    assert b"changed" not in M.encode(pairs_message(cubic_store(), "r", 1.0))
