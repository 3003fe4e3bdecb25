"""The order the suite's tests are handed to pytest-xdist in (tests/conftest.py calls :func:`order`).

``--dist worksteal`` first gives each of the N workers a contiguous share of the collected tests, in order, then a
worker whose share ran out takes the later half of the longest remaining share. Where a long test sits decides the
wall time: one that starts late (near the end of its share, or stolen at the end) ends the run alone while the
other workers wait. So the long tests are dealt out first: the longest to the share with the least long-test time so
far (longest processing time first), and in each share they start early, each followed by a stretch of quick tests
(not one long test after another on one worker: most of them are whole loops of processes on real time, and the
quick tests between them leave the cores to the loops). The quick tests keep their collected order (a file's tests
stay together), so the late halves the stealing moves are quick tests.

The long tests and their seconds are :data:`LONGEST`: every test that took 4 s or more in a ``make test`` (six workers
on two cores), measured by tests/cpu_report.py; a test marked ``slow`` that is not listed counts
:data:`SLOW_DEFAULT_S`. Listed whole, not only the longest: a share's time is in its long tests, so a test of 5-20 s
left among the quick ones sat wherever the collected order put it, and the run ended with such tests alone on a
worker or two while the other cores idled. A group of tests that share a module's fixtures moves whole with its long
tests. A name that no longer matches a collected test is simply not found: the order stays valid, only less
balanced. How long the suite takes: docs/BENCHMARKS.md, "The test suite"."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

#: node id -> seconds of wall time, for the tests that take at least a few (tests/durations.json, written by
#: ``python -m tests.cpu_report DIR --durations`` from a report of ``make test``'s own workers; the measure is only for
#: their order)
LONGEST: dict[str, float] = json.loads((Path(__file__).parent / "durations.json").read_text())
#: the seconds counted for a test marked ``slow`` that :data:`LONGEST` does not list
SLOW_DEFAULT_S = 10.0
#: the long tests of a share start within this part of it (the rest, quick tests only, is what stealing moves)
LONG_SPAN = 0.4


def shares(n_items: int, workers: int) -> list[int]:
    """The sizes of the contiguous shares ``--dist worksteal`` first hands the workers (xdist's own arithmetic: each
    idle worker in turn gets the remaining tests divided by the workers still to serve)."""
    out, left = [], n_items
    for i in range(workers):
        out.append(left // (workers - i))
        left -= out[-1]
    return out


def order(items: Sequence[T], workers: int, seconds: Callable[[T], float | None],
          group: Callable[[T], str] | None = None) -> list[T]:
    """``items`` reordered for ``workers`` xdist workers (see the module docstring); ``seconds(item)`` is an item's
    expected time if it is a long test, else None. A long test goes in only between two quick tests of different
    ``group`` (tests/conftest.py: the module, for a module with a module- or class-scoped fixture): one inside such a
    module's run of tests would end its fixtures there, and pytest would set them up again after it; and the long
    tests of one such group go one after another to one share (dealt apart, each worker would set up the fixture they
    share). Every item is kept, once."""
    keys: list[object] = [group(it) if group is not None else i for i, it in enumerate(items)]
    # a group with a long test moves whole, in its order (a module whose tests share its fixtures: split, its
    # fixtures would be set up again where its run resumes)
    moving = {k for k, it in zip(keys, items) if seconds(it) is not None}
    quick = [it for k, it in zip(keys, items) if k not in moving]
    units: dict[object, list[T]] = {}
    for k, it in zip(keys, items):
        if k in moving:
            units.setdefault(k, []).append(it)
    if not units:
        return list(items)

    def unit_s(unit: list[T]) -> float:
        return sum(seconds(it) or 0.0 for it in unit)

    workers = max(1, workers)
    sizes = shares(len(items), workers)
    bins: list[list[list[T]]] = [[] for _ in range(workers)]
    load = [0.0] * workers
    counts = [0] * workers
    for unit in sorted(units.values(), key=lambda u: -unit_s(u)):  # the longest first, each to the share with the
        k = min(range(workers), key=lambda i: (load[i], counts[i] - sizes[i]))  # least long-test time (ties: larger)
        bins[k].append(unit)
        load[k] += unit_s(unit)
        counts[k] += len(unit)
    out: list[T] = []
    q = 0
    for k in range(workers):
        n_quick = max(0, sizes[k] - counts[k])
        mine, q = quick[q:q + n_quick], q + n_quick
        gap = int(len(mine) * LONG_SPAN) // max(1, len(bins[k]))  # quick tests after each long one
        cut = 0
        for j, unit in enumerate(bins[k]):
            out.extend(unit)
            end = max(cut, min(len(mine), (j + 1) * gap))
            while group is not None and 0 < end < len(mine) and group(mine[end]) == group(mine[end - 1]):
                end += 1  # to the end of that module's run
            out.extend(mine[cut:end])
            cut = end
        out.extend(mine[cut:])
    out.extend(quick[q:])  # only when the long tests outnumber a share's size
    return out
