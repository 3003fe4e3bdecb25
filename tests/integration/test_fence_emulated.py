"""The fence upload against the emulated rover (sim_learner/mavlink_fence.py, written from ArduPilot's source): the
driver uploads and enables a person's polygon (drivers/mavlink/fence.py, every answer read), the rover drives at it,
the driver stops sending (its host died, no stop sent), and the vehicle's own fence sets HOLD at the line instead of
GUIDED carrying it on for its timeout. The same scenario on ArduPilot SITL: tests/integration/test_fence_sitl.py."""

from __future__ import annotations

import time

import pytest

from drivers import open_driver
from drivers.mavlink import MavlinkLinkConfig
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.vehicle import SimVehicle
from tests.wait import until

SQUARE = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]


def _rig(**rover_kw):
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4, guid_timeout=3.0, **rover_kw).start()
    driver = open_driver("mavlink", MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", open_timeout=10.0,
                                                      ack_timeout=0.3))
    return rover, vehicle, driver


@pytest.mark.timeout(60)
def test_the_vehicles_own_fence_holds_the_rover_when_the_host_dies() -> None:
    rover, vehicle, driver = _rig()
    try:
        driver.open(time.monotonic())
        said = driver.upload_fence(SQUARE)
        assert "4 vertices" in said and "enabled" in said, said
        assert rover.fence.enabled and len(rover.fence.polygon) == 4
        assert [c for p in rover.fence.polygon for c in p] == pytest.approx([c for p in SQUARE for c in p], abs=0.01)
        assert (rover.params["FENCE_TYPE"], rover.params["FENCE_ACTION"], rover.params["FENCE_ENABLE"]) == (4, 2, 1)
        driver.engage(time.monotonic())
        t_end = time.monotonic() + 10.0
        while vehicle.advance(time.monotonic()).x < 0.5 and time.monotonic() < t_end:  # full ahead, east
            driver.send(0.5, 0.0, time.monotonic())
            driver.poll(time.monotonic())
            time.sleep(0.02)  # pacing: the host's 50 Hz, inside a deadline loop that ends on the event
        assert vehicle.advance(time.monotonic()).x >= 0.5
        # the host dies: nothing more is sent, no stop either; GUIDED would carry it 1.5 m on (3 s at 0.5 m/s)
        until(lambda: rover.mode_name == "HOLD" and vehicle.state.v == 0.0, 20.0, 0.05)
        x = vehicle.advance(time.monotonic()).x
        assert rover.mode_name == "HOLD" and rover.fence.breaches == 1, (rover.mode_name, rover.statustexts[-3:])
        assert 1.0 <= x < 1.2, f"stopped at x = {x:.2f} (the fence at 1.0)"
        assert "Fence Breached" in rover.statustexts
    finally:
        driver.close(disarm=False, stop_timeout=0.0)
        rover.stop()
