"""The replay guard of a person's acts (:mod:`bridge.core.acts`): an act names the process it is for (its epoch)
and echoes that process's own clock; the window's edges, what each refusal counts and says, how long a nonce is
kept, the budgets per source, and :func:`stamped`. Times are arguments (the receiver's monotonic clock), nothing
sleeps. Over Zenoh against real driver hosts and stations, across restarts: tests/integration/test_acts.py."""

from __future__ import annotations

import time

import pytest

from bridge.core import wire as M
from bridge.core.acts import MAX_SOURCES, PER_SOURCE, WINDOW_S, ActGuard, Address, Refusal, address_of, stamped

EPOCH, NOW = 0x5EED, 5000.0  # the receiver's epoch and monotonic clock


def test_an_act_is_taken_for_its_own_process_once_while_its_echo_is_fresh() -> None:
    g = ActGuard(EPOCH)
    assert g.check(EPOCH, NOW - 1.0, "a", "operator", NOW) is None
    assert g.check(EPOCH, NOW - 1.0, "a", "operator", NOW + 0.5).kind == "replayed"
    assert g.check(EPOCH, NOW - 60.0, "b", "operator", NOW).kind == "stale"
    assert g.check(EPOCH, NOW + 1.0, "c", "operator", NOW).kind == "future"  # a clock reading not made yet
    assert g.check(0, NOW, "d", "operator", NOW).kind == "unaddressed"
    assert g.check(EPOCH, NOW, "", "operator", NOW).kind == "unstamped"
    assert g.check(EPOCH, 0.0, "e", "operator", NOW).kind == "unstamped"


def test_an_act_recorded_before_a_restart_is_refused_after_it_whatever_the_clocks() -> None:
    """Finding: a person's release, engage and resume captured, the host and the station SIGKILLed and restarted:
    replayed 7-9 s after capture, each was taken (the nonces lived in the dead process's memory). The new start has
    a new epoch: the recorded act names the old one. Its echo is fresh on the new start's clock (the same monotonic
    clock: a process restart is not a reboot) and no nonce table knows it: the epoch alone refuses it."""
    before, after = ActGuard(EPOCH), ActGuard(EPOCH + 1)  # the same host, started twice
    act = (EPOCH, NOW, "n1", "operator")
    assert before.check(*act, NOW + 0.1) is None
    got = after.check(*act, NOW + 8.0)
    assert got.kind == "other_process" and "another start" in got.text, got


def test_no_wall_clock_is_compared_so_a_clock_an_hour_off_refuses_nothing_and_revives_nothing() -> None:
    """Finding: with the robot's wall clock 1 h behind, every engage and release was refused; stepped +1 h and back,
    a captured engage was taken again. The guard reads no wall clock: the tool's wall_time is for the logs."""
    g = ActGuard(EPOCH)
    hour_off = stamped(M.EngageRequest(stamp=1.0, source="operator"), Address(EPOCH, NOW))
    hour_off = type(hour_off)(**{**{f: getattr(hour_off, f) for f in hour_off.__struct_fields__},
                                 "wall_time": time.time() - 3600.0})
    assert g.check(hour_off.target, hour_off.echo, hour_off.nonce, hour_off.source, NOW + 0.2) is None
    assert g.check(hour_off.target, hour_off.echo, hour_off.nonce, hour_off.source, NOW + 0.3).kind == "replayed"


def test_the_window_is_on_the_receivers_clock_and_inclusive() -> None:
    g = ActGuard(EPOCH)
    assert g.check(EPOCH, NOW - WINDOW_S, "edge", "operator", NOW) is None
    assert g.check(EPOCH, NOW - WINDOW_S - 1e-3, "old", "operator", NOW).kind == "stale"
    assert g.check(EPOCH, NOW, "now", "operator", NOW) is None


def test_every_refusal_is_counted_by_kind_and_says_refused_with_its_reason() -> None:
    g = ActGuard(EPOCH, window_s=5.0, per_source=1)
    got = [g.check(0, NOW, "n0", "op", NOW), g.check(EPOCH + 1, NOW, "n1", "op", NOW),
           g.check(EPOCH, NOW, "", "op", NOW), g.check(EPOCH, NOW - 7.5, "n2", "op", NOW),
           g.check(EPOCH, NOW + 1, "n3", "op", NOW)]
    assert g.check(EPOCH, NOW, "n4", "op", NOW) is None
    got += [g.check(EPOCH, NOW, "n4", "op", NOW), g.check(EPOCH, NOW, "n5", "op", NOW)]
    assert all(isinstance(r, Refusal) and r.text.startswith("refused: ") for r in got)
    assert [r.kind for r in got] == ["unaddressed", "other_process", "unstamped", "stale", "future", "replayed",
                                     "flooded"]
    assert all(v == 1 for v in g.refused.values())
    assert "7.5 s ago" in got[3].text and "more than 5 s" in got[3].text
    assert f"{EPOCH + 1:x}" in got[1].text and f"{EPOCH:x}" in got[1].text


def test_a_refused_act_leaves_no_nonce_and_a_nonce_is_kept_while_its_echo_is_fresh() -> None:
    g = ActGuard(EPOCH, window_s=10.0)
    assert g.check(EPOCH, NOW - 60.0, "n", "op", NOW).kind == "stale" and g.seen == {}
    assert g.check(EPOCH, NOW - 4.0, "n", "op", NOW) is None
    assert g.seen == {"op": {"n": NOW + 6.0}}
    assert g.check(EPOCH, NOW - 4.0, "n", "op", NOW + 5.9).kind == "replayed"
    assert g.check(EPOCH, NOW + 6.5, "m", "op", NOW + 6.5) is None
    assert g.seen == {"op": {"m": NOW + 16.5}}  # forgotten once its echo could no longer be fresh


def test_a_flood_by_one_source_never_refuses_anothers_act_and_a_persons_act_comes_first() -> None:
    """Finding: 4096 fresh acts filled the one nonce table and refused a person's engage as "flooded" for 19.8 s.
    Each source has its own budget; sources beyond MAX_SOURCES are refused, the configured persons never."""
    g = ActGuard(EPOCH, persons=("operator",))
    for i in range(PER_SOURCE + 50):
        g.check(EPOCH, NOW, f"f{i}", "mallory", NOW)
    assert g.refused["flooded"] == 50
    assert g.check(EPOCH, NOW, "mine", "operator", NOW) is None
    for s in range(MAX_SOURCES + 5):  # a flood of made-up sources
        g.check(EPOCH, NOW, f"s{s}", f"src{s}", NOW)
    assert g.check(EPOCH, NOW, "late", "src-new", NOW).kind == "flooded"
    assert g.check(EPOCH, NOW, "mine2", "operator", NOW) is None  # the person still acts
    assert g.check(EPOCH, NOW + WINDOW_S + 1, "later", "src-new", NOW + WINDOW_S + 1) is None  # expired


def test_the_defaults_are_the_documented_ones() -> None:
    g = ActGuard(EPOCH)
    assert (g.window_s, g.per_source, g.max_sources) == (WINDOW_S, PER_SOURCE, MAX_SOURCES) == (10.0, 256, 32)


@pytest.mark.parametrize("req", [
    M.EngageRequest(stamp=3.0, source="operator", clear_faults=True),
    M.MissionRequest(stamp=3.0, action="start", source="operator"),
    M.Estop(stamp=3.0, engaged=False, source="operator", reason="done"),
])
def test_stamped_addresses_the_act_with_a_new_nonce_and_keeps_the_rest(req) -> None:
    to = Address(EPOCH, NOW)
    a, b = stamped(req, to), stamped(req, to)
    assert req.nonce == "" and req.target == 0  # the original is left as it was
    assert (a.target, a.echo) == (EPOCH, NOW) and a.nonce != b.nonce and len(a.nonce) == 32
    for name in req.__struct_fields__:
        if name not in ("wall_time", "nonce", "target", "echo"):
            assert getattr(a, name) == getattr(req, name), name
    g = ActGuard(EPOCH)
    assert g.check(a.target, a.echo, a.nonce, a.source, NOW + 0.1) is None
    assert g.check(b.target, b.echo, b.nonce, b.source, NOW + 0.1) is None
    assert M.decode(M.encode(a), type(req)) == a
    first = stamped(req)  # a tool's first try names no process
    assert first.target == 0 and g.check(first.target, first.echo, first.nonce, first.source, NOW).kind == \
        "unaddressed"


def test_an_answer_gives_the_address_and_an_older_nodes_none() -> None:
    st = M.EngageState(stamp=12.5, node="driver", engaged=False, epoch=EPOCH)
    assert address_of(st) == Address(EPOCH, 12.5)
    assert address_of(M.EstopState(stamp=1.0, node="driver", latched=True)) is None
    old = M.encode(M.EngageRequest(stamp=1.0, source="operator"))  # an older tool's request decodes: target 0
    assert M.decode(old, M.EngageRequest).target == 0
