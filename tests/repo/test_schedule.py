"""The suite's order for pytest-xdist (tests/schedule.py): every test kept once, the long tests dealt out over the
workers' first shares with the longest first, each share's long tests early in it, and the listed long tests still
exist. Pure: no test is run, the items are names."""

from __future__ import annotations

import re
from pathlib import Path

from tests.schedule import LONG_SPAN, LONGEST, order, shares

ROOT = Path(__file__).resolve().parents[2]


def _suite(n_quick: int, long_s: dict[str, float]) -> tuple[list[str], dict[str, float]]:
    """``n_quick`` quick tests with the long ones scattered among them, in a collected order."""
    items = [f"q{i}" for i in range(n_quick)]
    for j, name in enumerate(long_s):
        items.insert((j * 37) % len(items), name)
    return items, long_s


def test_xdist_shares_are_its_own_arithmetic() -> None:
    assert shares(10, 4) == [2, 2, 3, 3] and sum(shares(2752, 4)) == 2752 and shares(5, 1) == [5]


def test_every_test_is_kept_once_and_the_quick_ones_keep_their_order() -> None:
    items, long_s = _suite(500, {f"L{k}": float(60 - 3 * k) for k in range(14)})
    out = order(items, 4, long_s.get)
    assert sorted(out) == sorted(items)
    assert [it for it in out if it.startswith("q")] == [it for it in items if it.startswith("q")]
    assert order(items, 4, lambda it: None) == items  # nothing long: the collected order


def test_the_long_tests_start_early_in_each_share_longest_first_and_the_shares_carry_alike() -> None:
    long_s = {"L0": 51.0, "L1": 45.0, "L2": 40.0, "L3": 35.0, "L4": 34.0, "L5": 32.0, "L6": 31.0, "L7": 30.0,
              "L8": 24.0, "L9": 20.0, "L10": 10.0}
    items, _ = _suite(800, long_s)
    workers = 4
    out = order(items, workers, long_s.get)
    start = 0
    carried = []
    for size in shares(len(out), workers):
        share = out[start:start + size]
        start += size
        where = [i for i, it in enumerate(share) if it in long_s]
        mine = [share[i] for i in where]
        assert where and where[0] == 0, share[:3]  # each share starts with a long test
        assert max(where) <= LONG_SPAN * size, where  # and its long ones are in its early part, not its tail
        assert [long_s[it] for it in mine] == sorted((long_s[it] for it in mine), reverse=True)
        assert all(b - a > 1 for a, b in zip(where, where[1:])), where  # quick tests between two long ones
        carried.append(sum(long_s[it] for it in mine))
    assert sorted(out[i] for i in range(len(out)) if out[i] in long_s) == sorted(long_s)
    assert max(carried) - min(carried) <= max(long_s.values()) / 2, carried  # balanced: within half the longest
    assert {out[0], out[shares(len(out), workers)[0]]} <= {"L0", "L1", "L2", "L3"}  # the longest go first


def test_every_listed_long_test_still_exists() -> None:
    """A renamed or removed test in LONGEST would silently fall back to the collected order's place for it."""
    for nodeid in LONGEST:
        path, name = nodeid.split("::", 1)
        func = re.sub(r"\[.*\]$", "", name)
        text = (ROOT / path).read_text()
        assert re.search(rf"^def {re.escape(func)}\(", text, re.M), nodeid


def test_a_long_test_never_splits_a_modules_run_of_tests() -> None:
    """A long test put inside another module's run would end that module's module-scoped fixtures there (pytest sets
    them up again after it): the long ones go in only where the quick tests' module changes."""
    items = [f"m{m}::t{t}" for m in range(40) for t in range(7)]
    long_s = {f"L{k}::t": float(50 - k) for k in range(9)}
    for j, name in enumerate(long_s):
        items.insert(j * 30, name)
    out = order(items, 4, long_s.get, group=lambda it: it.split("::")[0])
    assert sorted(out) == sorted(items)
    quick = [it for it in out if not it.startswith("L")]
    assert quick == [it for it in items if not it.startswith("L")]
    for i, it in enumerate(out[1:-1], 1):
        if it in long_s:
            before, after = out[i - 1], out[i + 1]
            if before not in long_s and after not in long_s:
                assert before.split("::")[0] != after.split("::")[0], (before, it, after)


def test_the_long_tests_of_a_module_that_shares_a_fixture_run_one_after_another_on_one_worker() -> None:
    """Dealt apart, two workers would each set up the module-scoped fixture the long tests share (test_drift.py's
    seed sweeps): they go together, in their order, as one long unit of their summed seconds."""
    items = [f"m{m}::t{t}" for m in range(40) for t in range(7)]
    long_s = {"drift::wheel": 24.0, "drift::floor": 23.0, **{f"L{k}::t": float(30 - k) for k in range(6)}}
    for j, name in enumerate(long_s):
        items.insert(j * 30, name)
    out = order(items, 4, long_s.get, group=lambda it: it.split("::")[0])
    assert sorted(out) == sorted(items)
    i = out.index("drift::wheel")
    assert out[i + 1] == "drift::floor"
    assert i == 0  # the longest unit (47 s) first


def test_a_module_that_shares_a_fixture_moves_whole_with_its_long_test() -> None:
    """test_experiments.py's sweep: one long test and the quick ones that read the same module-scoped fixture. Left
    among the quick tests, those would set the fixture up a second time where the module's run resumes: the module
    goes as one unit, in its order, dealt out early as its long test is."""
    items = [f"m{m}::t{t}" for m in range(40) for t in range(7)]
    sweep = ["sweep::json", "sweep::goal", "sweep::time", "sweep::dev"]
    items[200:200] = sweep
    long_s = {"sweep::goal": 20.0, **{f"L{k}::t": float(30 - k) for k in range(6)}}
    for j, name in enumerate(n for n in long_s if not n.startswith("sweep")):
        items.insert(j * 30, name)
    out = order(items, 4, long_s.get, group=lambda it: it.split("::")[0])
    assert sorted(out) == sorted(items)
    i = out.index("sweep::json")
    assert out[i:i + 4] == sweep  # together, in their collected order
    share = next(s for s in _share_slices(len(out), 4) if s.start <= i < s.stop)
    assert i - share.start <= LONG_SPAN * (share.stop - share.start)  # early in its share, not where it was collected


def _share_slices(n: int, workers: int) -> list[slice]:
    out, start = [], 0
    for size in shares(n, workers):
        out.append(slice(start, start + size))
        start += size
    return out
