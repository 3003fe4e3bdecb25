"""The driver host's loop on a fake clock (``tests/fakeclock.py``): its real scheduler, gate, link (the CAN driver on a
python-can ``virtual`` bus, two ODrive controllers played by :mod:`tests.odrive_play`) and status, with time moved
only by the loop's own waits. So the deadman, the send budget, the wake on a command and the status cadence are
checked to the tick, on any machine, without sleeping (docs/ARCHITECTURE.md section 4, "Threads and clocks")."""

from __future__ import annotations

import threading
import uuid
from collections.abc import Iterator

import pytest

from bridge.core import wire as M
from bridge.nodes.driver_config import DriverConfig, DriverSection
from bridge.nodes.driver_host import SEND_BURST, DriverHost
from drivers.can import CanDriver, CanLinkConfig
from tests.fakeclock import FakeClock
from tests.odrive_play import Controllers

RATE = 50.0


class Out:
    """A publisher's stand-in that keeps what was put, with the fake time it was put at."""

    def __init__(self, clock: FakeClock, kind: type) -> None:
        self.clock, self.kind = clock, kind
        self.got: list[tuple[float, M.Msg]] = []

    def put(self, payload: bytes) -> None:
        self.got.append((self.clock.t, M.decode(payload, self.kind)))


class HostRig:
    def __init__(self, clock: FakeClock, **driver: object) -> None:
        self.clock = clock
        channel = f"host-{uuid.uuid4().hex[:8]}"
        self.controllers = Controllers(channel, clock, encoders=True)
        clock.on_read.append(self.controllers.step)
        self.link = CanDriver(CanLinkConfig(interface="virtual", channel=channel, heartbeat_timeout=0.3,
                                            open_timeout=1.0), clock=clock)
        cfg = DriverConfig(driver=DriverSection(**driver))  # type: ignore[arg-type]
        self.host = DriverHost(cfg, "can", self.link, "r1", RATE, clock=clock)
        self.applied, self.status = Out(clock, M.Applied), Out(clock, M.Status)
        self.host.pubs = {"applied": self.applied, "state": Out(clock, M.LearnerState), "status": self.status}
        self.stop = threading.Event()
        self.seq = 0

    def engage(self) -> None:
        self.link.open(self.clock())
        ans = self.host.handle_engage(M.EngageRequest(stamp=0.0, source="test"), self.clock())
        assert ans.engaged, ans.text

    def command_at(self, t: float, v: float = 0.3) -> None:
        """A station's command delivered at fake time ``t`` (the gate's own checks apply)."""
        def deliver() -> None:
            self.seq += 1
            self.host.on_cmd(M.Command(stamp=self.clock.t, seq=self.seq, v=v, omega=0.0, method="scm",
                                       valid_ms=300, sender="station", epoch=7), self.clock.t)
        self.clock.at(t, deliver)

    def run(self, duration: float) -> None:
        self.host.loop(self.stop, duration)

    def close(self) -> None:
        self.link.close(stop_timeout=0.0)
        self.controllers.bus.shutdown()


@pytest.fixture
def rig(clock: FakeClock) -> Iterator[HostRig]:
    r = HostRig(clock)
    try:
        yield r
    finally:
        r.close()


def _driving(rig: HostRig) -> list[tuple[float, M.Applied]]:
    return [(t, a) for t, a in rig.applied.got if a.v != 0.0]


def test_without_commands_the_vehicle_stops_within_the_deadman_to_the_tick(rig: HostRig) -> None:
    rig.engage()
    t0 = rig.clock.t
    for k in range(10):  # a station at 10 Hz for 1 s, then silent
        rig.command_at(t0 + 0.05 + 0.1 * k)
    last_cmd = t0 + 0.05 + 0.9
    rig.run(2.0)
    driving = _driving(rig)
    assert driving and driving[0][0] == pytest.approx(t0 + 0.05)  # the command woke the loop: applied at once
    first_stop = next(t for t, a in rig.applied.got if t > last_cmd and a.v == 0.0)
    timeout = rig.host.gate.cmd_timeout
    assert last_cmd + timeout - 1e-9 <= first_stop <= last_cmd + timeout + 1.0 / RATE + 1e-9
    assert all(a.v == 0.0 for t, a in rig.applied.got if t >= first_stop)


def test_a_lost_link_stops_the_vehicle_within_its_heartbeat_timeout(rig: HostRig) -> None:
    rig.engage()
    t0 = rig.clock.t
    for k in range(20):
        rig.command_at(t0 + 0.05 + 0.1 * k)
    lost = t0 + 0.5
    rig.clock.at(lost, lambda: rig.controllers.muted.update({0, 1}))  # the bus goes silent
    rig.run(1.5)
    stops = [t for t, a in rig.applied.got if t > lost and a.v == 0.0]
    assert stops, "the host never stopped"
    # heard last at most one Heartbeat period before the loss; the timeout; then the tick that notices
    assert stops[0] - lost <= 0.3 + 1.0 / RATE + 1e-9
    assert all(a.v == 0.0 for t, a in rig.applied.got if t >= stops[0])
    status = [s for _, s in rig.status.got]
    assert status[-1].ok is False


def test_a_flood_of_commands_gets_the_link_no_more_than_the_send_budget(clock: FakeClock) -> None:
    rig = HostRig(clock, max_send_hz=100.0)
    try:
        rig.engage()
        t0 = clock.t
        for k in range(2000):  # a command every 0.5 ms for 1 s: 2000 wake-ups
            rig.command_at(t0 + 0.0005 * (k + 1))
        rig.run(1.0)
        ticks = [t for t, _ in rig.applied.got]
        assert len(ticks) <= SEND_BURST + 100.0 * 1.0 + 1
        assert len(ticks) >= 90  # the budget is spent, not starved
        gaps = [b - a for a, b in zip(ticks[SEND_BURST:], ticks[SEND_BURST + 1:])]
        assert min(gaps) >= 1.0 / 100.0 - 1e-9
    finally:
        rig.close()


def test_status_goes_out_each_second_and_at_once_on_a_change(rig: HostRig) -> None:
    rig.engage()
    t0 = rig.clock.t
    for k in range(40):
        rig.command_at(t0 + 0.05 + 0.1 * k)
    estop_at = t0 + 2.5
    rig.clock.at(estop_at, lambda: rig.host.on_estop(
        M.Estop(stamp=0.0, engaged=True, source="operator", reason="test"), rig.clock.t))
    rig.run(4.0)
    times = [t for t, _ in rig.status.got]
    latched = [t for t, s in rig.status.got if s.reason == "estop"]
    assert latched and latched[0] == pytest.approx(estop_at)  # at once: the estop woke the loop
    periodic = [t for t in times if t < estop_at]
    gaps = [b - a for a, b in zip(periodic, periodic[1:])]
    assert gaps and all(g == pytest.approx(1.0, abs=1.0 / RATE + 1e-9) or g < 1.0 for g in gaps)
    assert len(times) <= 4.0 + 4  # each second, plus the changes: not one per tick


def test_the_link_is_judged_once_per_tick(rig: HostRig) -> None:
    rig.engage()
    t0 = rig.clock.t
    for k in range(10):
        rig.command_at(t0 + 0.05 + 0.1 * k)
    judged = rig.link.judged
    rig.run(1.0)
    ticks = len(rig.applied.got)
    assert ticks >= 50
    assert rig.link.judged - judged <= ticks  # poll, the host's health and send share one verdict
