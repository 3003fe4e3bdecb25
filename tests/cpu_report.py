"""Where the suite's CPU goes, test by test: an opt-in pytest plugin and its report (docs/BENCHMARKS.md, "The test
suite").

``SCMBRIDGE_CPU_REPORT=DIR python -m pytest -p tests.cpu_report ...`` writes one JSON line per test to
``DIR/<worker>.jsonl``: the CPU its worker spent on it (``self``) and that of the processes the test started and
reaped (``children``), both user + system from ``resource.getrusage`` around the test's setup, call and teardown, its
wall time, when it started (the wall clock, shared by the workers) and its worker; each worker's last line is its whole
session (``__total__``). A process reaped later (by another test's
``subprocess.Popen``, which reaps the finished children it finds) counts there, and one never reaped not at all.
``python -m tests.cpu_report DIR [N]`` prints the totals, the CPU by group and module, the N costliest tests, and the
run's tail: when each worker ran out of tests and which tests ended last. ``python -m tests.cpu_report DIR
--durations > tests/durations.json`` writes the long tests the suite's order deals out first (tests/schedule.py)."""

from __future__ import annotations

import collections
import json
import os
import resource
import sys
import time
from pathlib import Path
from typing import IO

import pytest

ENV = "SCMBRIDGE_CPU_REPORT"
#: the wall time from which a test counts as long for the suite's order (:func:`durations`)
MIN_LONG_S = 4.0
_out: IO[str] | None = None


def _cpu() -> tuple[float, float]:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime, c.ru_utime + c.ru_stime


def _write(row: dict) -> None:
    global _out
    if not os.environ.get(ENV):
        return
    if _out is None:
        Path(os.environ[ENV]).mkdir(parents=True, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        _out = open(Path(os.environ[ENV]) / f"{worker}.jsonl", "a", buffering=1)  # noqa: SIM115 (the session's)
    _out.write(json.dumps(row) + "\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    (s0, c0), w0, t0 = _cpu(), time.monotonic(), time.time()
    yield
    (s1, c1), w1 = _cpu(), time.monotonic()
    _write({"id": item.nodeid, "self": round(s1 - s0, 3), "children": round(c1 - c0, 3), "wall": round(w1 - w0, 3),
            "start": round(t0, 3), "worker": os.environ.get("PYTEST_XDIST_WORKER", "main")})


def pytest_sessionfinish(session: pytest.Session) -> None:
    if os.environ.get("PYTEST_XDIST_WORKER"):  # the controller's children are the workers: counted already
        s, c = _cpu()
        _write({"id": "__total__", "self": round(s, 3), "children": round(c, 3)})


def _read(directory: Path) -> tuple[list[dict], list[float]]:
    """The report's rows, one per test, and the workers' own and children's CPU summed."""
    rows, total = [], [0.0, 0.0]
    for f in sorted(directory.glob("*.jsonl")):
        for line in f.read_text().splitlines():
            r = json.loads(line)
            if r["id"] == "__total__":
                total[0], total[1] = total[0] + r["self"], total[1] + r["children"]
            else:
                rows.append(r)
    return rows, total


def durations(directory: Path, min_s: float = MIN_LONG_S) -> dict[str, float]:
    """The tests of a report that took at least ``min_s`` of wall time, longest first: what tests/durations.json
    holds for the suite's order (tests/schedule.py), from a report of ``make test``'s own workers."""
    rows, _ = _read(directory)
    long = {r["id"]: round(r["wall"], 1) for r in rows if r["wall"] >= min_s}
    return dict(sorted(long.items(), key=lambda kv: (-kv[1], kv[0])))


def report(directory: Path, n: int = 30) -> str:
    rows, total = _read(directory)

    def cpu(r: dict) -> float:
        return r["self"] + r["children"]

    groups: collections.Counter[str] = collections.Counter()
    modules: collections.Counter[str] = collections.Counter()
    for r in rows:
        path = r["id"].split("::")[0]
        groups["/".join(path.split("/")[1:3 if path.startswith("tests/unit/sim_learner") else 2])] += cpu(r)
        modules[path] += cpu(r)
    out = [f"workers: {total[0]:.1f} CPU-s own + {total[1]:.1f} of their children; {len(rows)} tests: "
           f"{sum(map(cpu, rows)):.1f} CPU-s, {sum(r['wall'] for r in rows):.1f} s of wall time summed",
           "by group: " + ", ".join(f"{k} {v:.1f}" for k, v in groups.most_common())]
    out += [f"{v:7.1f}  {k}" for k, v in modules.most_common(n)]
    out += [f"{cpu(r):7.1f}  (own {r['self']:.1f}, children {r['children']:.1f}, wall {r['wall']:.1f})  {r['id']}"
            for r in sorted(rows, key=cpu, reverse=True)[:n]]
    return "\n".join(out + _tail(rows))


def _tail(rows: list[dict]) -> list[str]:
    """When each worker ran out of tests, relative to the first test's start, and the tests that ended last: the
    run's tail, where fewer workers than cores are busy (rows without a start, from an older report, are left out)."""
    timed = [r for r in rows if "start" in r]
    if not timed:
        return []
    t0 = min(r["start"] for r in timed)
    ends: dict[str, float] = {}
    for r in timed:
        ends[r["worker"]] = max(ends.get(r["worker"], 0.0), r["start"] + r["wall"] - t0)
    last = max(ends.values())
    out = [f"workers out of tests at (s after the first test's start; the last at {last:.0f}): "
           + ", ".join(f"{w} {e:.0f}" for w, e in sorted(ends.items(), key=lambda kv: kv[1])),
           f"idle worker-seconds before the last ended: {sum(last - e for e in ends.values()):.0f}",
           "the tests that ended last (start, wall):"]
    for r in sorted(timed, key=lambda r: r["start"] + r["wall"], reverse=True)[:8]:
        out.append(f"  {r['start'] - t0:6.0f} {r['wall']:6.1f}  {r['worker']}  {r['id']}")
    return out


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[2] == "--durations":  # DIR --durations: the suite's order's long tests
        print(json.dumps(durations(Path(sys.argv[1])), indent=1))
    else:
        print(report(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 30))
