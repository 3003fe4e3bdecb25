"""The replay guard of a person's acts (:mod:`bridge.core.acts`): the window's edges, what each refusal counts and
says, how long a nonce is kept, and :func:`stamped`. Times are arguments (a fake wall clock), nothing sleeps.

The guard's basic contract (fresh and once, stale, future, unstamped, flooded) is also exercised in
tests/integration/test_acts.py, which drives it through the driver host and the station over Zenoh."""

from __future__ import annotations

import time

import pytest

from bridge.core import wire as M
from bridge.core.acts import MAX_NONCES, WINDOW_S, ActGuard, Refusal, stamped

NOW = 1.7e9  # a wall-clock time (s since the epoch), passed in


def test_the_window_is_inclusive_on_both_sides_and_its_edges_are_refused_just_beyond() -> None:
    g = ActGuard()
    assert g.check(NOW - WINDOW_S, "old-edge", NOW) is None  # exactly WINDOW_S old: still fresh
    assert g.check(NOW + WINDOW_S, "new-edge", NOW) is None  # exactly WINDOW_S ahead: still fresh
    assert g.check(NOW - WINDOW_S - 1e-3, "old", NOW).kind == "stale"
    assert g.check(NOW + WINDOW_S + 1e-3, "new", NOW).kind == "future"


def test_every_refusal_is_counted_by_kind_and_says_refused_with_its_reason() -> None:
    g = ActGuard(window_s=5.0, max_nonces=1)
    got = [
        g.check(0.0, "n0", NOW),  # unstamped: no time
        g.check(NOW, "", NOW),  # unstamped: no nonce
        g.check(NOW - 7.5, "n1", NOW),  # stale
        g.check(NOW + 12.4, "n2", NOW),  # future
    ]
    assert g.check(NOW, "n3", NOW) is None
    got.append(g.check(NOW, "n3", NOW))  # replayed
    got.append(g.check(NOW, "n4", NOW))  # flooded: one nonce kept at most
    assert all(isinstance(r, Refusal) and r.text.startswith("refused: ") for r in got)
    assert [r.kind for r in got] == ["unstamped", "unstamped", "stale", "future", "replayed", "flooded"]
    assert g.refused == {"unstamped": 2, "stale": 1, "future": 1, "replayed": 1, "flooded": 1}
    # the texts name the figures a person needs: how far off, and the window
    assert "7.5 s ago" in got[2].text and "more than 5 s" in got[2].text and "NTP" in got[2].text
    assert "12.4 s ahead" in got[3].text and "more than 5 s" in got[3].text
    assert "more than 1 requests within 5 s" in got[5].text


def test_a_refused_request_leaves_no_nonce_behind() -> None:
    """Only a taken request's nonce is kept: a stale or future one may be sent again once the clocks agree."""
    g = ActGuard()
    assert g.check(NOW - 60.0, "n", NOW).kind == "stale"
    assert g.check(NOW + 60.0, "m", NOW).kind == "future"
    assert g.seen == {}
    assert g.check(NOW, "n", NOW) is None and g.check(NOW, "m", NOW) is None


def test_a_nonce_is_kept_until_its_request_could_no_longer_be_fresh_then_forgotten() -> None:
    g = ActGuard(window_s=10.0)
    assert g.check(NOW - 4.0, "past", NOW) is None  # stamped 4 s ago: kept until NOW + 10
    assert g.check(NOW + 3.0, "ahead", NOW) is None  # stamped ahead: kept until its own time + 10
    assert g.seen == {"past": NOW + 10.0, "ahead": NOW + 13.0}
    assert g.check(NOW - 4.0, "past", NOW + 5.9).kind == "replayed"  # still fresh (9.9 s old): a replay
    assert g.check(NOW + 3.0, "ahead", NOW + 12.9).kind == "replayed"
    g.check(NOW + 13.5, "other", NOW + 13.5)
    assert set(g.seen) == {"other"}  # both forgotten once they could no longer be fresh


def test_a_flood_is_refused_until_the_kept_nonces_expire() -> None:
    g = ActGuard(window_s=1.0, max_nonces=3)
    assert [g.check(NOW, f"n{i}", NOW) for i in range(3)] == [None, None, None]
    assert g.check(NOW + 0.5, "late", NOW + 0.5).kind == "flooded"
    assert g.check(NOW + 1.5, "later", NOW + 1.5) is None  # the first three expired at NOW + 1
    assert set(g.seen) == {"later"}


def test_the_defaults_are_the_documented_ones() -> None:
    g = ActGuard()
    assert (g.window_s, g.max_nonces) == (WINDOW_S, MAX_NONCES) == (10.0, 4096)


@pytest.mark.parametrize("req", [
    M.EngageRequest(stamp=3.0, source="operator", clear_faults=True),
    M.MissionRequest(stamp=3.0, action="start", source="operator"),
    M.Estop(stamp=3.0, engaged=False, source="operator", reason="done"),
])
def test_stamped_adds_the_wall_time_and_a_new_nonce_and_keeps_the_rest(req) -> None:
    before = time.time()
    a, b = stamped(req), stamped(req)
    after = time.time()
    assert req.wall_time == 0.0 and req.nonce == ""  # the original is left as it was
    assert before <= a.wall_time <= after and before <= b.wall_time <= after
    assert a.nonce != b.nonce and len(a.nonce) == 32 and int(a.nonce, 16) >= 0  # 128 random bits in hex
    assert type(a) is type(req)
    for name in req.__struct_fields__:
        if name not in ("wall_time", "nonce"):
            assert getattr(a, name) == getattr(req, name), name
    g = ActGuard()
    assert g.check(a.wall_time, a.nonce, after) is None  # what a tool sends is taken by a guard with the same clock
    assert g.check(b.wall_time, b.nonce, after) is None
    assert M.decode(M.encode(a), type(req)) == a  # and travels as it is
