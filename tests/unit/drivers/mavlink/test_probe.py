""":class:`drivers.mavlink.probe.Probe`: a read-only look at the vehicle over the driver's link, against the emulated
rover (sim_learner/mavlink_rover.py: real pymavlink framing over UDP on 127.0.0.1, a free port)."""

from __future__ import annotations

import time

import pytest

from drivers.mavlink import MavlinkLinkConfig
from drivers.mavlink.probe import Probe
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.vehicle import SimVehicle


def test_the_probe_hears_the_vehicle_reads_its_parameters_and_changes_nothing() -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with MavlinkRover(vehicle, init_s=0.1, ekf_position_s=0.2, wp_speed=0.6) as rover:
        probe = Probe(MavlinkLinkConfig(url=f"udpout:127.0.0.1:{rover.port}", source_system=1,
                                        source_component=191))
        try:
            assert probe.wait(lambda: probe.heartbeat is not None, 5.0)
            p = probe.read_params(("WP_SPEED", "FS_ACTION", "NO_SUCH_PARAM"), 2.0)
            assert p == pytest.approx({"WP_SPEED": 0.6, "FS_ACTION": 2.0})  # an unknown name: no answer, left out
            assert probe.signed_from_vehicle == 0 and probe.carrying_signature == 0
        finally:
            probe.close()
        assert rover.mode_name == "MANUAL" and not rover.armed
