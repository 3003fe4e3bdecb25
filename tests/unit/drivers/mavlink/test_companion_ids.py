"""``[link.mavlink] source_system`` / ``source_component``: the ids the driver host speaks with beside a ground station
(docs/OPERATING.md, "First day with your rover")."""

from __future__ import annotations

import pytest

from bridge.core.config import Rule
from drivers.mavlink.config import MavlinkLinkConfig


def test_a_ground_stations_ids_by_default_and_a_companions_when_configured() -> None:
    gcs = MavlinkLinkConfig()
    assert (gcs.source_system, gcs.source_component, gcs.companion) == (255, 190, False)
    comp = MavlinkLinkConfig(source_system=1, source_component=191)
    assert comp.companion


def test_the_autopilots_own_ids_are_refused() -> None:
    with pytest.raises(Rule, match="autopilot's own ids"):
        MavlinkLinkConfig(source_system=1, source_component=1)
    MavlinkLinkConfig(source_system=2, source_component=1, target_system=2, target_component=191)  # not the same


def test_a_companion_speaks_with_its_ids_says_it_is_one_and_takes_acks_addressed_to_it() -> None:
    """Real pymavlink over UDP on 127.0.0.1: the vehicle end sees the HEARTBEAT from (1, 191) typed
    MAV_TYPE_ONBOARD_CONTROLLER, and an ACK addressed to (1, 191) is the command's; one to a ground station's
    (255, 190) beside it on the radio is a stray."""
    from pymavlink import mavutil

    from drivers.base import LinkHealth
    from drivers.mavlink import load_pymavlink
    from drivers.mavlink.client import MavlinkClient
    from tests.fakeclock import FakeClock

    mav = mavutil.mavlink
    clock = FakeClock()
    vehicle = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
    cfg = MavlinkLinkConfig(url=f"udpout:127.0.0.1:{vehicle.port.getsockname()[1]}", source_system=1,
                            source_component=191)
    client = MavlinkClient(cfg, load_pymavlink(), LinkHealth(), {"stray_acks": 0}, on_message=lambda m: None,
                           clock=clock)
    client.on_message = lambda m: client.ack(m) if m.get_type() == "COMMAND_ACK" else None
    client.connect(clock.t)
    try:
        client.heartbeat(clock.t, force=True)
        hb = vehicle.recv_match(type="HEARTBEAT", blocking=True, timeout=2.0)
        assert hb is not None and (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 191)
        assert hb.type == mav.MAV_TYPE_ONBOARD_CONTROLLER
        c = client.submit(mav.MAV_CMD_REQUEST_MESSAGE, (148,), "autopilot version")
        assert vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=2.0) is not None
        vehicle.mav.command_ack_send(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_RESULT_ACCEPTED, 0, 0, 255, 190)
        vehicle.mav.command_ack_send(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_RESULT_ACCEPTED, 0, 0, 1, 191)
        client.wait(lambda: c.result is not None, clock.t + 1.0)
        assert c.result == mav.MAV_RESULT_ACCEPTED and client.counts["stray_acks"] == 1
    finally:
        client.close()
        vehicle.close()
