"""drivers/base.py: the link protocol's own pieces (docs/ARCHITECTURE.md, "Links"): :func:`whole_numbers` (what a
link's detail reports as counters), :func:`link_unauthenticated` (what the driver host and ``doctor`` say about a link
anyone may command), the value types (:class:`Pose`, :class:`LinkHealth`, :class:`FailsafeReport`) and the
runtime-checkable :class:`Driver` protocol. The links themselves are tested under tests/unit/drivers/ (can/, mavlink/,
test_udp.py); a plugin link against this protocol in tests/unit/drivers/test_registry.py."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest

from drivers.base import (
    Driver,
    DriverError,
    FailsafeReport,
    LinkBase,
    LinkHealth,
    Pose,
    counter_names,
    link_unauthenticated,
    whole_numbers,
)


@dataclass(frozen=True)
class _Detail:
    refusals: int = 3
    engaged: bool = True
    idle: bool = False
    offset: int = -2  # not a count: below zero
    ratio: float = 0.5  # not a whole number
    mode: str = "GUIDED"
    missing: int | None = None


def test_whole_numbers_keeps_the_counts_and_flags_not_below_zero_by_name() -> None:
    assert whole_numbers(_Detail()) == {"refusals": 3, "engaged": 1, "idle": 0}
    out = whole_numbers(_Detail(refusals=0, offset=7))
    assert out == {"refusals": 0, "engaged": 1, "idle": 0, "offset": 7}
    assert all(type(v) is int for v in out.values())  # flags become 0/1, as the status counters carry them


def test_whole_numbers_refuses_what_is_not_a_dataclass() -> None:
    with pytest.raises(TypeError):
        whole_numbers({"refusals": 3})


def test_link_unauthenticated_repeats_the_configs_own_words_or_says_nothing() -> None:
    class Insecure:
        def unauthenticated(self) -> str:
            return "insecure = true"

    class Signed:
        def unauthenticated(self) -> str:
            return ""

    class Wire:  # a CAN bus: nothing to say
        pass

    class NotAMethod:
        unauthenticated = "a field, not a method"

    assert link_unauthenticated(Insecure()) == "insecure = true"
    assert link_unauthenticated(Signed()) == ""
    assert link_unauthenticated(Wire()) == ""
    assert link_unauthenticated(NotAMethod()) == ""
    assert link_unauthenticated(None) == ""


def test_the_real_links_configs_say_whether_they_authenticate() -> None:
    from drivers.can.config import CanLinkConfig
    from drivers.mavlink.config import MavlinkLinkConfig

    assert link_unauthenticated(CanLinkConfig()) == ""
    assert "signing is off" in link_unauthenticated(MavlinkLinkConfig())
    assert link_unauthenticated(MavlinkLinkConfig(signing_key_file="/k")) == ""


def test_a_pose_is_a_frozen_value_whose_speeds_are_optional() -> None:
    p = Pose(1.0, 2.0, 3.0, 0.5)
    assert (p.v, p.omega) == (None, None)
    assert p == Pose(1.0, 2.0, 3.0, 0.5, None, None) and hash(p) == hash(Pose(1.0, 2.0, 3.0, 0.5))
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.x = 9.0  # type: ignore[misc]


def test_link_health_starts_closed_not_ok_with_zero_counts() -> None:
    h = LinkHealth()
    assert (h.connected, h.ok, h.reason, h.text, h.detail) == (False, False, "closed", "not opened", None)
    assert (h.frames_sent, h.frames_received, h.malformed, h.errors) == (0, 0, 0, 0)
    # ``reason`` is last: a positional construction of the earlier fields keeps its meaning
    assert [f.name for f in dataclasses.fields(LinkHealth)][-1] == "reason"
    positional = LinkHealth(True, True, "ok", 1, 2, 3, 4)
    assert (positional.errors, positional.reason) == (4, "closed")


def test_failsafe_reports_do_not_share_their_settings() -> None:
    a, b = FailsafeReport(None, "unknown"), FailsafeReport(1.5, "stops after 1.5 s")
    assert a.params == {} and a.params is not b.params
    assert FailsafeReport(1.5, "x", {"FS_TIMEOUT": 1.5}).params == {"FS_TIMEOUT": 1.5}


def test_driver_error_is_a_runtime_error_with_its_reason() -> None:
    with pytest.raises(RuntimeError, match="vehicle refused to arm"):
        raise DriverError("vehicle refused to arm")


def test_the_driver_protocol_is_checked_at_run_time_on_every_member() -> None:
    class Complete:
        name = "complete"

        def open(self, now): ...
        def engage(self, now, clear_faults=False): ...
        def failsafe(self): ...
        def send(self, v, omega, now): ...
        def stop(self, now): ...
        def poll(self, now): return []
        def health(self, now): return LinkHealth()
        def clear_faults(self, now): ...
        def close(self, disarm=True, stop_speed=0.05, stop_timeout=3.0): ...

    assert isinstance(Complete(), Driver)
    assert not isinstance(object(), Driver)
    partial = type("Partial", (), {"name": "p", "open": lambda self, now: None})
    assert not isinstance(partial(), Driver)


def test_the_shipped_drivers_satisfy_the_protocol() -> None:
    from drivers.can import CanDriver, CanLinkConfig
    from drivers.mavlink import MavlinkDriver, MavlinkLinkConfig

    assert isinstance(CanDriver(CanLinkConfig()), Driver)  # construction does no I/O
    assert isinstance(MavlinkDriver(MavlinkLinkConfig()), Driver)


# ------------------------------------------------------------------------------------------------ LinkBase
@dataclass(frozen=True)
class _Counts:
    """A link's counters dataclass: the one place its counts are named."""

    sent: int = 0
    lost: int = 0
    faults: int = 0  # kept by another piece of the link
    mode: str = ""  # not a count
    ratio: float = 0.0  # not a count


class _Link(LinkBase):
    """A link on the base: a vehicle whose reported speed falls by ``slows`` each stop, fit while ``fit``."""

    COUNTERS = _Counts
    COUNTED_ELSEWHERE = ("faults",)

    def __init__(self, clock, speed: float = 1.0, slows: float = 0.25) -> None:
        super().__init__(clock)
        self.speed, self.slows = speed, slows
        self.stops: list[float] = []
        self.fit = True

    def _judge_link(self, now: float):
        return (self.fit, "ok" if self.fit else "link_down", "ready" if self.fit else "down")

    def stop(self, now: float) -> None:
        self.stops.append(now)
        self.speed = max(0.0, self.speed - self.slows)


def test_counter_names_come_from_the_counters_dataclass_alone() -> None:
    assert counter_names(_Counts) == ("sent", "lost", "faults")
    assert counter_names(_Counts, besides=("faults",)) == ("sent", "lost")


def test_a_links_counts_are_made_from_its_counters_dataclass_and_report_as_it(clock) -> None:
    link = _Link(clock)
    assert link.counts == {"sent": 0, "lost": 0}
    link.counts["sent"] += 2
    assert link.counters == {"sent": 2, "lost": 0} and link.counters is not link.counts
    assert link._counter_snapshot(faults=1, mode="GUIDED") == _Counts(sent=2, lost=0, faults=1, mode="GUIDED")


def test_the_verdict_is_judged_once_per_moment_until_something_changes(clock) -> None:
    link = _Link(clock)
    assert link._verdict(5.0) == (True, "ok", "ready")
    link.fit = False  # changed without saying so: the moment's verdict stands
    assert link._verdict(5.0) == (True, "ok", "ready") and link.judged == 1
    link._changed()
    assert link._verdict(5.0) == (False, "link_down", "down") and link.judged == 2
    assert link._verdict(5.02) == (False, "link_down", "down") and link.judged == 3  # a new moment: judged again


def test_closing_stops_until_the_vehicle_reports_slower_than_stop_speed_then_once_more(clock) -> None:
    link = _Link(clock, speed=1.0, slows=0.25)
    t0 = clock.t
    assert link._stop_until_still(t0, 0.05, 3.0, 0.02, lambda now: link.speed)
    assert len(link.stops) == 5 and link.speed == 0.0  # four to slow from 1.0 to 0, one after
    assert link.stops[:4] == pytest.approx([t0 + 0.02 * k for k in range(4)])
    assert clock.slept == pytest.approx(0.08)  # the waits moved the fake clock: nothing slept for real


def test_closing_gives_up_after_stop_timeout_and_still_stops(clock) -> None:
    link = _Link(clock, speed=1.0, slows=0.0)  # a vehicle that never reports slowing down
    t0 = clock.t
    assert not link._stop_until_still(t0, 0.05, 0.5, 0.02, lambda now: link.speed)
    assert clock.t == pytest.approx(t0 + 0.5) and link.stops[-1] == pytest.approx(t0 + 0.5)
    unknown = _Link(clock)
    assert not unknown._stop_until_still(clock.t, 0.05, 0.0, 0.02, lambda now: None)  # no time: one stop only
    assert len(unknown.stops) == 1


def test_a_link_whose_close_takes_no_now_is_still_closed_and_one_that_takes_it_gets_the_hosts() -> None:
    """A lab's own link written before ``close`` took the host's ``now`` still stops its vehicle at shutdown."""
    from drivers.base import close_link

    calls: list[dict] = []

    class Old:
        def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0) -> None:
            calls.append({"disarm": disarm, "stop_timeout": stop_timeout})

    class New:
        def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
                  now: float | None = None) -> None:
            calls.append({"disarm": disarm, "now": now})

    class Kw:
        def close(self, **kw: object) -> None:
            calls.append(dict(kw))

    close_link(Old(), 12.5, disarm=False, stop_timeout=0.0)
    close_link(New(), 12.5, disarm=True)
    close_link(Kw(), 3.0, disarm=False)
    assert calls == [{"disarm": False, "stop_timeout": 0.0}, {"disarm": True, "now": 12.5},
                     {"disarm": False, "now": 3.0}]
