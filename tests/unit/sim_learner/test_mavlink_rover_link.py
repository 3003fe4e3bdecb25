"""The emulated rover's udp transport (sim_learner/mavlink_rover_link.py): it answers the last peer heard, and
what it is sent waits in the read buffer for the GCS tick; a blackout drops both ways."""

from __future__ import annotations

import socket
import time

from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.vehicle import SimVehicle


def test_udp_answers_the_last_peer_heard_and_a_blackout_drops_both_ways() -> None:
    rover = MavlinkRover(SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic()))
    rover._open()
    try:
        assert not rover.connected
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            peer.bind(("127.0.0.1", 0))
            peer.settimeout(2.0)
            peer.sendto(b"abc", ("127.0.0.1", rover.port))
            t_end = time.monotonic() + 2.0
            while not rover._rx and time.monotonic() < t_end:
                rover._drain()
            assert bytes(rover._rx) == b"abc" and rover.connected and rover._peer == peer.getsockname()
            rover._transmit(b"xyz")
            assert peer.recvfrom(64)[0] == b"xyz"
            rover.blackout = True
            rover._rx.clear()
            peer.sendto(b"lost", ("127.0.0.1", rover.port))
            time.sleep(0.05)  # (a datagram on loopback; nothing announces that it was dropped)
            rover._drain()
            assert not rover._rx
    finally:
        rover._close()
