"""Decisions read typed reasons, never words (issue 30): rewording a link's or a node's ``text`` changes nothing the
robot does. Each decision that once parsed a text (the driver host's ``applied`` reason, its following of the
MAVLink operator and its state; the station's estop, its ``ok`` and its pause; ``scmbridge status``'s verdict) is
driven here with the same typed reason under unrelated words, and with misleading words under another reason."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.core import wire as M
from bridge.core.config import StationConfig, load_mission
from bridge.nodes.driver_config import DriverConfig
from bridge.nodes.driver_host import DriverHost
from bridge.nodes.engagement import blocked_reason
from bridge.nodes.mission_control import MissionControl, spec_of
from bridge.nodes.sources import Proposal, Why
from bridge.nodes.station_core import StationCore, TickInputs
from bridge.nodes.station_fitness import driver_estop
from bridge.tools.status import robot_ok
from drivers.base import LinkHealth

#: words that once decided (``operator...``, ``estop latched``, ``calibration:``, ``driving``) and words that did not
TEXTS = ["operator took control: mode HOLD", "the pilot has the vehicle", "", "estop latched by operator",
         "calibration: plan finished", "driving", "goal reached"]


class _Link:
    """A link whose health is what the test says (the host's decisions on it are under test, not a link)."""

    name = "fixed"

    def __init__(self, health: LinkHealth, operator_engages: bool) -> None:
        self.h = health
        self.operator_engages = operator_engages

    def health(self, now: float) -> LinkHealth:
        return self.h

    def clear_faults(self, now: float) -> None:
        pass


def _host(reason: str, text: str, operator_engages: bool, now: float) -> DriverHost:
    """An engaged host with a fresh pose and a fresh command to drive, on a link not fit for the given reason."""
    health = LinkHealth(connected=True, ok=False, text=text, reason=reason)
    host = DriverHost(DriverConfig(), "mavlink", _Link(health, operator_engages), "r1", 50.0)
    host.engaged, host.engagement.was_ok, host.engagement.was_connected, host.poses.last_pose = True, True, True, now
    host.on_cmd(M.Command(stamp=now, seq=1, v=0.2, omega=0.0, method="scm", sender="station", epoch=7), now)
    return host


@pytest.mark.parametrize("text", TEXTS)
def test_the_driver_host_follows_the_operator_by_the_links_reason_whatever_its_words(text: str) -> None:
    now = 10.0
    operator = _host("operator", text, operator_engages=True, now=now)
    assert operator.decide(now).reason == "disengaged" and not operator.engaged  # MAVLink: the operator took it
    assert operator.node_state(False, operator.health, 0.0, [text]) == ("waiting", "not_engaged")
    fault = _host("fault", text, operator_engages=True, now=now)
    assert fault.decide(now).reason == "fault" and fault.engaged  # not the operator: still engaged, stopped
    assert fault.node_state(False, fault.health, 0.0, [text]) == ("fault", "fault")


@pytest.mark.parametrize("text", TEXTS)
def test_the_applied_reason_and_the_hosts_state_come_from_the_links_reason(text: str) -> None:
    now = 10.0
    host = _host("operator", text, operator_engages=False, now=now)  # a link whose operator does not engage (CAN)
    assert host.decide(now).reason == "operator" and host.engaged
    assert host.node_state(False, host.health, 0.0, [text]) == ("operator", "operator")
    status = host.status(now)
    assert (status.state, status.reason, status.ok) == ("operator", "operator", False)
    for reason in ("rebooted", "disarmed", "no_telemetry", "fault", "no_heartbeat", "odometry", "arming"):
        h = LinkHealth(connected=True, ok=False, text=text, reason=reason)
        assert blocked_reason(h) == "fault", reason
    assert blocked_reason(LinkHealth(connected=True, ok=False, text=text, reason="operator")) == "operator"
    assert blocked_reason(LinkHealth(connected=False, ok=False, text=text, reason="operator")) == "link_down"


def test_a_latched_estop_is_the_driver_hosts_reason_also_in_a_dry_run() -> None:
    now = 10.0
    host = _host("fault", "anything", operator_engages=False, now=now)
    host.gate.estop(M.Estop(stamp=0.0, source="operator", reason="test"))
    st = host.status(now)
    assert (st.state, st.reason) == ("estop", "estop")
    host.options.dry_run = True
    st = host.status(now)
    assert (st.state, st.reason) == ("dry_run", "estop")
    assert driver_estop(st)


# ------------------------------------------------------------------------------------------------ station
def _driver(ok: bool, state: str, reason: str | None, text: str, seq: int = 1) -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=ok, state=state, reason=reason, text=text)


@pytest.mark.parametrize("text", TEXTS)
def test_the_station_sees_an_estop_by_the_driver_hosts_reason_whatever_its_words(tmp_path, text: str) -> None:
    pose = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=-1.0, theta=0.0)
    cases = [(_driver(False, "dry_run", "estop", text), True),  # a dry run's estop: only the reason says it
             (_driver(False, "estop", "estop", text), True),
             (_driver(False, "fault", "fault", text), False),
             (_driver(False, "estop", None, text), True),  # a host older than the reason: its state says it
             (_driver(False, "fault", None, text), False)]
    for k, (driver, estop) in enumerate(cases):
        core = StationCore(StationConfig(), "r1", 10.0, tmp_path / f"{k}.bin", load_mission())
        core.tick(TickInputs(telemetry=((pose, 1.0),), driver=(driver, 1.0)), 1.0)
        assert core.verdict.fitness.estop is estop, (driver, estop)
        ans = core.request(M.MissionRequest(stamp=1.0, action="start", source="test"), 1.0)
        assert ans.accepted is not estop and core.control.phase == ("idle" if estop else "running"), ans


class _Says:
    """A command source that drives once, then stops with the given words and typed reason."""

    what, follows_mission, external = "says", False, False

    def __init__(self, why: Why) -> None:
        self.why, self.asked = why, 0

    def propose(self, now, pose, ctx):
        self.asked += 1
        return Proposal(np.array([0.2, 0.0]), np.array([pose.x, pose.y])) if self.asked == 1 else self.why

    def reset(self) -> None:
        pass

    def done(self) -> bool:
        return False


@pytest.mark.parametrize("text", TEXTS)
def test_the_stations_ok_and_state_come_from_its_typed_reason_whatever_its_words(tmp_path, text: str) -> None:
    pose = M.LearnerState(stamp=1.0, seq=1, x=0.0, y=-1.0, theta=0.0)
    fit = _driver(True, "driving", "ok", "link can: driving (cmd)")
    for k, (why, ok) in enumerate([(Why(text, "calibration_done"), True), (Why(text), False),
                                   (Why(text, "goal_reached"), True)]):
        core = StationCore(StationConfig(), "r1", 10.0, tmp_path / f"{k}.bin", load_mission(), source=_Says(why))
        core.request(M.MissionRequest(stamp=0.0, action="start", source="test"), 0.0)
        first = core.tick(TickInputs(telemetry=((pose, 1.0),), driver=(fit, 1.0)), 1.0)
        assert first.command.method != "stop" and core.verdict.reason == "ok" and core.status(1.0).state == "driving"
        core.tick(TickInputs(telemetry=((pose, 1.1),), driver=(fit, 1.1)), 1.1)
        st = core.status(1.1)
        assert (st.ok, st.reason, st.text) == (ok, why.reason, text), st
        assert st.state == "waiting"  # the mission runs, the source stops it: whatever the words say
        core.saves.error = "pair store not saved: No space left on device"
        st = core.status(1.2)
        assert not st.ok and st.reason == ("persist_failed" if ok else why.reason)


def test_a_paused_mission_whose_reason_is_empty_still_stops(tmp_path) -> None:
    """Finding: the station drove a paused mission whose saved reason was empty (an empty ``why`` meant "drive")."""
    mission = load_mission()
    control = MissionControl("r1", spec_of(mission), "paused", "")
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission, control=control)
    pose = M.LearnerState(stamp=1.0, seq=1, x=float(mission.start[0]), y=float(mission.start[1]),
                          theta=float(mission.start[2]))
    for k in range(3):
        now = 1.0 + 0.1 * k
        out = core.tick(TickInputs(telemetry=((pose, now),), driver=(_driver(True, "driving", "ok", "", k), now)),
                        now)
        assert out.command.method == "stop" and core.verdict.reason == "paused" and control.phase == "paused"
    st = core.status(1.3)
    assert (st.ok, st.state, st.reason) == (False, "paused", "paused")


@pytest.mark.parametrize("text", TEXTS)
def test_scmbridge_status_judges_a_robot_by_the_stations_reason(text: str) -> None:
    driver = (_driver(True, "driving", "ok", text), 0.0)

    def station(ok: bool, state: str, reason: str | None) -> tuple[M.Status, float]:
        return M.Status(stamp=0.0, seq=1, node="station", ok=ok, state=state, reason=reason, text=text), 0.0

    assert robot_ok({"station": station(True, "driving", "ok"), "driver": driver}, 1.0)
    assert robot_ok({"station": station(True, "finished", "goal_reached"), "driver": driver}, 1.0)
    assert not robot_ok({"station": station(True, "waiting", "calibration_done"), "driver": driver}, 1.0)
    assert not robot_ok({"station": station(False, "paused", "paused"), "driver": driver}, 1.0)
    assert robot_ok({"station": station(True, "driving", None), "driver": driver}, 1.0)  # an older station
    assert not robot_ok({"station": station(True, "paused", None), "driver": driver}, 1.0)


def test_a_status_without_a_reason_decodes_and_the_reason_is_checked() -> None:
    old = M.encode(M.Status(stamp=1.0, seq=1, node="driver", ok=False, state="estop", text="link can: estop"))
    assert b"reason" not in old and M.decode(old, M.Status).reason is None
    new = M.Status(stamp=1.0, seq=1, node="driver", ok=False, state="estop", reason="estop")
    assert M.validated(new).reason == "estop"
    bad = M.encode(new).replace(b"estop", b"esto!")
    with pytest.raises(M.MessageError):
        M.decode(bad, M.Status)
