"""tests/cpu_report.py's report: the CPU totals and the run's tail, from rows written as its plugin writes them."""

from __future__ import annotations

import json

from tests.cpu_report import report


def _rows(path, rows) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_the_report_sums_the_cpu_and_names_the_worker_and_the_test_that_ended_last(tmp_path) -> None:
    _rows(tmp_path / "gw0.jsonl", [
        {"id": "tests/unit/a/test_x.py::t1", "self": 1.0, "children": 0.5, "wall": 2.0, "start": 100.0,
         "worker": "gw0"},
        {"id": "tests/integration/test_y.py::long", "self": 0.1, "children": 9.0, "wall": 30.0, "start": 102.0,
         "worker": "gw0"},
        {"id": "__total__", "self": 3.0, "children": 9.5}])
    _rows(tmp_path / "gw1.jsonl", [
        {"id": "tests/unit/a/test_x.py::t2", "self": 2.0, "children": 0.0, "wall": 4.0, "start": 100.5,
         "worker": "gw1"},
        {"id": "__total__", "self": 2.5, "children": 0.0}])
    text = report(tmp_path, 5)
    assert text.splitlines()[0].startswith("workers: 5.5 CPU-s own + 9.5 of their children; 3 tests: 12.6 CPU-s")
    assert "workers out of tests at (s after the first test's start; the last at 32): gw1 4, gw0 32" in text
    assert "idle worker-seconds before the last ended: 28" in text
    tail = text.split("the tests that ended last (start, wall):\n", 1)[1].splitlines()
    assert tail[0].split() == ["2", "30.0", "gw0", "tests/integration/test_y.py::long"]


def test_rows_of_an_older_report_without_start_times_give_no_tail(tmp_path) -> None:
    _rows(tmp_path / "gw0.jsonl", [{"id": "tests/unit/a/test_x.py::t1", "self": 1.0, "children": 0.0, "wall": 1.0}])
    text = report(tmp_path, 5)
    assert text.splitlines()[0].startswith("workers: 0.0 CPU-s own + 0.0 of their children; 1 tests: 1.0 CPU-s")
    assert "workers out of tests" not in text and text.rstrip().endswith("tests/unit/a/test_x.py::t1")
