"""The robot-side speed limiter on a real driver host process (``scmbridge driver --link can --emulate`` with
``v_accel`` / ``omega_accel`` in ``[driver.hard_limits]``) over a real Zenoh session on 127.0.0.1: a raw publisher on
``scm/<robot>/cmd`` (as an external program would) sends a step from rest to the top, and the applied echoes ramp
within the acceleration limit; a stop reaches the vehicle as exactly zero at once."""

from __future__ import annotations

import os
import time

from bridge.core import wire as M
from bridge.core.wire import Keys, status_key
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import spawn, stop_group
from tests.collect import Collector

V_ACCEL, W_ACCEL = 0.5, 1.0


def test_a_raw_step_reaches_the_wheels_as_a_ramp_and_a_stop_at_once(tmp_path) -> None:
    port, robot = free_port(), f"lim{os.getpid()}"
    cfg = tmp_path / "driver.toml"
    cfg.write_text(f"[driver.hard_limits]\nv = [-0.5, 0.5]\nw = [-1.0, 1.0]\nv_accel = {V_ACCEL}\n"
                   f"omega_accel = {W_ACCEL}\n")
    proc = spawn(["driver", "--engage", "--link", "can", "--emulate", "--x0", "0,0,0", "--config", str(cfg),
                  "--robot", robot, "--listen", tcp(port), "--duration", "40"])
    try:
        with open_session(make_config(connect=[tcp(port)])) as session:
            col = Collector(session)
            keys = Keys(robot)
            applied = col.listen(keys.applied, M.Applied)
            status = col.listen(status_key(robot, "driver"), M.Status)
            assert col.wait(lambda: bool(status) and status[-1].ok, 20.0), "driver host did not come up"
            pub = session.declare_publisher(keys.cmd)
            seq, t0 = 0, time.monotonic()
            # the step: the top at once, sent at 20 Hz until the echo says the vehicle got it (deadline-bound)
            while time.monotonic() - t0 < 8.0:
                seq += 1
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=0.5, omega=-1.0, method="direct",
                                           valid_ms=300, sender="raw", epoch=7)))
                time.sleep(0.05)  # pacing: the raw sender's 20 Hz, inside a deadline loop that ends on the echo
                with col.lock:
                    if any(a.v == 0.5 and a.omega == -1.0 for a in applied):
                        break
            seq += 1
            t_stop = time.monotonic()
            pub.put(M.encode(M.Command(stamp=t_stop, seq=seq, v=0.0, omega=0.0, method="stop", valid_ms=300,
                                       sender="raw", epoch=7)))
            assert col.wait(lambda: any(a.reason == "stop" for a in applied), 20.0)
            got = col.snapshot(keys.applied)
    finally:
        stop_group(proc)
    driving = [a for a in got if a.reason in ("cmd", "clamped")]
    assert driving, "the vehicle never drove"
    assert driving[-1].v == 0.5 and driving[-1].omega == -1.0, "the ramp never reached the command"
    ramp = [a for a in driving if a.reason == "clamped"]
    assert len(ramp) >= 10, f"a step from rest to 0.5 m/s at {V_ACCEL} m/s² ramps over ~1 s: {len(ramp)} echoes"
    prev_t, prev_v, prev_w = None, 0.0, 0.0
    for a in driving:  # each echo's change within accel * interval (the first from rest, one tick's worth)
        dt = 0.04 if prev_t is None else min(0.04, a.stamp - prev_t)  # (the limiter's step is two periods at most)
        assert abs(a.v - prev_v) <= V_ACCEL * dt + 1e-9, (a, prev_v, dt)
        assert abs(a.omega - prev_w) <= W_ACCEL * dt + 1e-9, (a, prev_w, dt)
        prev_t, prev_v, prev_w = a.stamp, a.v, a.omega
    assert driving[0].v <= V_ACCEL * 0.04 + 1e-9  # not a step
    first_stop = next(a for a in got if a.reason == "stop")
    assert (first_stop.v, first_stop.omega) == (0.0, 0.0)  # the stop: exactly zero, not ramped down
    assert first_stop.stamp - driving[-1].stamp < 0.5
