"""The fence held by the autopilot itself (drivers/mavlink/fence.py), on ArduPilot's real Rover firmware in SITL
(sim_learner/sitl.py; marked ``sitl``): the driver host uploads a person's fence (``scmbridge driver --fence FILE``:
the polygon, FENCE_TYPE, FENCE_ACTION Hold, FENCE_ENABLE, each confirmed by the vehicle), drives the rover straight
at it, and then the base station dies mid-run (the driver host killed with SIGKILL, so nothing sends the vehicle a
stop). GUIDED would carry the last velocity on for its own 3 s timeout, 4.5 m at this speed: past the fence. The
autopilot holds its fence: Rover's avoidance (AC_Avoid, on by default with a fence) slows the vehicle to a stop its
margin inside the fence, and a breach would set HOLD (``Rover::fence_check`` with FENCE_ACTION Hold). Measured on
SITL: it stopped about 2 m inside the fence line (the avoidance margin), in GUIDED."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children
from sim_learner.sitl import Sitl
from tests.collect import Collector
from tests.integration.test_sitl import _sitl_binary

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]

#: the fence: a square of this half-side around the vehicle's start (the EKF origin), m
HALF = 6.0
#: the speed it is driven at, m/s: GUIDED's 3 s timeout alone would carry it 4.5 m past where the host died
SPEED = 1.5


def test_the_autopilots_fence_stops_the_rover_after_the_station_and_its_driver_host_die(tmp_path) -> None:
    binary = _sitl_binary()
    port, robot = free_port(), f"fence{os.getpid()}"
    fence = tmp_path / "station.toml"
    fence.write_text(f"[station]\nfence = [[{-HALF}, {-HALF}], [{HALF}, {-HALF}], [{HALF}, {HALF}], "
                     f"[{-HALF}, {HALF}]]\n")
    with Sitl(binary, model="rover-skid") as sitl, \
            open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        cfg = tmp_path / "driver.toml"
        cfg.write_text("[driver.hard_limits]\nv = [-2.0, 2.0]\nw = [-1.0, 1.0]\n\n"
                       f'[link.mavlink]\nurl = "{sitl.driver_url}"\nrate_hz = 20\n')
        col = Collector(session)
        status = col.listen(M.status_key(robot, "driver"), M.Status)
        host = kids.spawn(["driver", "--engage", "--link", "mavlink", "--config", str(cfg), "--fence", str(fence),
                           "--robot", robot, "--mode", "client", "--connect", tcp(port), "--duration", "200"])
        assert col.wait(lambda: bool(status) and status[-1].ok, 90.0), (
            f"the host did not drive: {[s.text for s in status[-2:]]}{kids.said()}")
        pilot = sitl.pilot
        assert pilot.param("FENCE_ENABLE") == 1 and pilot.param("FENCE_TYPE") == 4
        assert pilot.param("FENCE_ACTION") == 2  # Hold
        pub = session.declare_publisher(M.key(robot, "cmd"))
        stop = threading.Event()

        def station() -> None:  # the station's commands: straight ahead, 20 Hz, each valid 300 ms
            seq = 0
            while not stop.wait(0.05):
                seq += 1
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=SPEED, omega=0.0, method="direct",
                                           valid_ms=300)))

        thread = threading.Thread(target=station, daemon=True)
        thread.start()
        try:
            near = pilot.wait(lambda s: s.position is not None and max(abs(s.position.x), abs(s.position.y))
                              >= HALF - 3.5 and pilot._speed(s.position) > 0.8 * SPEED, 40.0)
            assert near, f"the rover did not head for the fence: at {pilot.position}, {pilot.speed:.2f} m/s"
            os.kill(host.pid, signal.SIGKILL)  # the base station dies: no stop is ever sent
        finally:
            stop.set()
            thread.join(2)
        died_at, t_died = pilot.position, time.monotonic()
        # stopped, and no longer carried by GUIDED's last target (its own timeout is 3 s)
        held = pilot.wait(lambda s: time.monotonic() > t_died + 4.0 and pilot._speed(s.position) < 0.05, 15.0)
        north, east = pilot.position
        mode, texts = pilot.mode, pilot.texts()
    out = max(abs(north), abs(east))
    assert held, f"the rover did not stop: mode {mode}, at ({north:.2f}, {east:.2f}); said {texts[-5:]}"
    assert max(abs(died_at[0]), abs(died_at[1])) <= HALF - 2.0, died_at  # far inside, fast, when the host died
    assert out < HALF + 0.5, f"stopped at ({north:.2f}, {east:.2f}), {out - HALF:+.2f} m past the fence ({mode})"
