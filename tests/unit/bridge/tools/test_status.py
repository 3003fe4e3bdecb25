"""``scmbridge status`` formatting and judging (:mod:`bridge.tools.status`): one node's line (silent, its reason in
words, progress, pairs, the pose's age), a driver host's estop by its typed reason or its state, a robot judged
fine or not when a node is stale or missing, the report's order and its missing/silent lines, its arguments, and
:class:`Seen` fed by a real Zenoh session. Arrival times are passed in (now minus an age); nothing sleeps.

How a robot is judged by its station's typed reason whatever the words is in
tests/unit/bridge/nodes/test_reasons.py; parked and estop at the goal in tests/integration/test_operator_truths.py;
the command itself over Zenoh in tests/integration/test_status.py."""

from __future__ import annotations

import argparse
import time

import pytest
import zenoh

from bridge.core import wire as M
from bridge.nodes.zsession import make_config
from bridge.tools import status as S
from bridge.tools.status import STALE_S, Seen, driver_estop, node_line, report, robot_ok

DRIVING = M.Status(stamp=0.0, seq=1, node="station", ok=True, state="driving", reason="ok", text="driving",
                   progress=0.42, counters={"refined_pairs": 17})
DRIVER = M.Status(stamp=0.0, seq=1, node="driver", ok=True, state="driving", reason="ok", text="link can: ok",
                  latencies_ms={"telemetry_age": 20.0})
ESTOP = M.Status(stamp=0.0, seq=1, node="driver", ok=False, state="estop", reason="estop",
                 text="link can: estop latched by operator")


def _seen(nodes: dict[tuple[str, str], tuple[M.Status, float]]) -> Seen:
    """A :class:`Seen` holding each status, arrived ``age`` seconds ago."""
    s, now = Seen(), time.monotonic()
    for k, (st, age) in nodes.items():
        s.latest[k] = (st, now - age)
    return s


def test_a_nodes_line_is_its_state_its_reason_and_what_a_person_needs_at_a_glance() -> None:
    line = node_line("rover1", "station", DRIVING, 0.5)
    assert line.split()[:3] == ["rover1", "station", "driving"]
    assert line.endswith("driving | mission 42% | pairs 17")
    assert node_line("rover1", "driver", DRIVER, 0.2).endswith("link can: ok | pose 0.02 s old")
    never = M.Status(stamp=0.0, seq=1, node="driver", ok=False, reason="no_telemetry",
                     latencies_ms={"telemetry_age": 1e9})
    assert node_line("r", "driver", never, 0.0).endswith("no_telemetry | pose never")  # no text: the reason
    bare = M.Status(stamp=0.0, seq=1, node="x", ok=False)
    assert node_line("r", "x", bare, 0.0) == f"{'r':<12} {'x':<8} {'not ok':<9} not ok"  # an old node: no state


def test_a_node_not_heard_for_longer_than_stale_is_silent() -> None:
    assert "silent" not in node_line("r", "driver", DRIVER, STALE_S)
    line = node_line("r", "driver", DRIVER, STALE_S + 4.6)
    assert line.split()[2] == "silent" and "no status for 8 s (the node is down or unreachable)" in line


def test_a_driver_estop_is_its_typed_reason_or_for_an_older_host_its_state() -> None:
    assert driver_estop(ESTOP)
    assert not driver_estop(M.Status(stamp=0.0, seq=1, node="driver", state="estop", reason="operator"))  # typed wins
    assert driver_estop(M.Status(stamp=0.0, seq=1, node="driver", state="estop"))  # an older host: no reason
    assert not driver_estop(DRIVER)


def test_a_robot_is_fine_only_with_both_nodes_fresh_no_estop_and_its_station_driving() -> None:
    now = 100.0
    assert robot_ok({"station": (DRIVING, now - 1.0), "driver": (DRIVER, now - 1.0)}, now)
    assert not robot_ok({"station": (DRIVING, now - STALE_S - 0.1), "driver": (DRIVER, now)}, now)
    assert not robot_ok({"station": (DRIVING, now), "driver": (DRIVER, now - STALE_S - 0.1)}, now)
    assert not robot_ok({"station": (DRIVING, now)}, now)
    assert not robot_ok({"driver": (DRIVER, now)}, now)
    assert not robot_ok({"station": (DRIVING, now), "driver": (ESTOP, now)}, now)
    old = M.Status(stamp=0.0, seq=1, node="station", ok=True)  # an older station: no state, no reason
    assert robot_ok({"station": (old, now), "driver": (DRIVER, now)}, now)


def test_the_report_lists_the_station_then_the_driver_then_the_rest_and_judges_all() -> None:
    extra = M.Status(stamp=0.0, seq=1, node="mocap", ok=True, text="bridge up")
    seen = _seen({("r1", "mocap"): (extra, 0.1), ("r1", "driver"): (DRIVER, 0.1), ("r1", "station"): (DRIVING, 0.1),
                  ("r2", "station"): (DRIVING, 0.1), ("r2", "driver"): (DRIVER, 0.1)})
    lines, ok = report(seen, None)
    assert ok and [ln.split()[:2] for ln in lines] == [["r1", "station"], ["r1", "driver"], ["r1", "mocap"],
                                                       ["r2", "station"], ["r2", "driver"]]
    lines, ok = report(seen, ["r2"])
    assert ok and {ln.split()[0] for ln in lines} == {"r2"}


def test_the_report_names_what_is_missing_or_silent_and_says_not_fine() -> None:
    lines, ok = report(_seen({("r1", "driver"): (DRIVER, 0.1)}), ["r1", "r3"])
    assert not ok
    assert lines[0].split()[:3] == ["r1", "station", "missing"] and "estop still reaches it" in lines[0]
    assert lines[1].split()[:3] == ["r1", "driver", "driving"]
    assert lines[2].split()[:3] == ["r3", "-", "silent"] and lines[2].endswith("no node of this robot answered")
    lines, ok = report(_seen({("r1", "station"): (DRIVING, 0.1)}), ["r1"])
    assert not ok and lines[0].split()[:3] == ["r1", "driver", "missing"] and "scmbridge doctor" in lines[0]
    lines, ok = report(_seen({("r1", "station"): (DRIVING, 10.0), ("r1", "driver"): (DRIVER, 0.1)}), ["r1"])
    assert not ok and lines[0].split()[2] == "silent"


def test_a_driving_driver_beside_a_parked_station_is_shown_parked() -> None:
    parked = M.Status(stamp=0.0, seq=1, node="station", ok=True, state="parked", reason="goal_reached")
    seen = _seen({("r1", "station"): (parked, 0.1), ("r1", "driver"): (DRIVER, 0.1)})
    lines, ok = report(seen, ["r1"])
    assert ok and lines[1].split()[2] == "parked"
    assert seen.latest[("r1", "driver")][0].state == "driving"  # what was heard is left as it was


def test_the_arguments_ask_for_one_robot_some_or_all() -> None:
    ap = argparse.ArgumentParser()
    S.arguments(ap)
    a = ap.parse_args(["--robots", "r1,r2"])
    assert a.robots == ["r1", "r2"] and not a.all and a.timeout == 1.5 and not a.watch
    assert ap.parse_args(["--all", "--timeout", "0.5", "--watch"]).timeout == 0.5
    for argv in ([], ["--robot", "r1", "--all"], ["--robot", "r1", "--timeout", "0"]):
        with pytest.raises(SystemExit):
            ap.parse_args(argv)


def test_seen_keeps_the_latest_status_per_robot_and_node_and_counts_what_does_not_decode() -> None:
    seen = Seen()
    with zenoh.open(make_config()) as session:  # one session: its own puts reach its subscriber
        sub = session.declare_subscriber("scm/*/status/**", seen.on_sample)
        session.put(M.status_key("r1", "driver"), M.encode(ESTOP))
        session.put(M.status_key("r1", "driver"), M.encode(DRIVER))
        session.put(M.status_key("r1", "station"), b"\xc1 not a status")
        session.put("scm/r1/status/driver/extra", M.encode(DRIVER))  # not scm/<robot>/status/<node>: not kept
        t_end = time.monotonic() + 10
        while time.monotonic() < t_end and not (seen.malformed and seen.latest.get(("r1", "driver"), (None,))[0]
                                                == DRIVER):
            time.sleep(0.01)
        sub.undeclare()
    assert seen.malformed == 1 and set(seen.latest) == {("r1", "driver")}
    st, at = seen.latest[("r1", "driver")]
    assert st == DRIVER and at <= time.monotonic()
