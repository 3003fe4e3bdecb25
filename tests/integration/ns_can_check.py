"""Run inside a private network namespace (see test_can_cross_process.py): driver host and learner emulator in
separate processes over python-can ``udp_multicast``, commands over Zenoh on the namespace's loopback.
Exit 0 when the commanded learner moved and the deadman stopped it, 1 otherwise."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

from bridge.core import wire as M
from bridge.core.wire import Keys
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import stop_group


def main() -> int:
    channel = "239.74.163.7"
    port = free_port()
    with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
        f.write(f'robot = "ns"\n[link.can]\ninterface = "udp_multicast"\nchannel = "{channel}"\nopen_timeout = 10.0\n')
        cfg = f.name
    py = [sys.executable, "-m", "bridge"]
    # the motor controllers first (they must answer the driver's arming), then the driver host
    learner = subprocess.Popen(py + ["learner", "--link", "can", "--interface", "udp_multicast", "--channel", channel,
                                     "--duration", "60"], stdout=subprocess.PIPE, text=True, start_new_session=True)
    procs = [learner]
    assert learner.stdout is not None
    learner.stdout.readline()  # "learner on ...": its bus is up
    procs.append(subprocess.Popen(py + ["driver", "--engage", "--link", "can", "--config", cfg, "--listen", tcp(port),
                                        "--duration", "60"], start_new_session=True))
    states: list[M.LearnerState] = []
    applied: list[M.Applied] = []
    ok = False
    try:
        with open_session(make_config(connect=[tcp(port)])) as s:
            k = Keys("ns")
            s.declare_subscriber(k.state, lambda x: states.append(M.decode(x.payload.to_bytes(), M.LearnerState)))
            s.declare_subscriber(k.applied, lambda x: applied.append(M.decode(x.payload.to_bytes(), M.Applied)))
            pub = s.declare_publisher(k.cmd)
            t_end = time.monotonic() + 20
            while not states and time.monotonic() < t_end:
                time.sleep(0.1)  # the poll step: until the first state
            x_start = states[-1].x if states else None
            for seq in range(1, 31):
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=0.3, omega=0.0, method="scm")))
                time.sleep(0.05)  # pacing: a station's 20 Hz
            t_end = time.monotonic() + 20
            while not any(a.reason == "deadman" for a in applied) and time.monotonic() < t_end:
                time.sleep(0.05)  # the poll step: until the deadman stopped it (the commands stopped)
            moved = x_start is not None and states[-1].x > x_start + 0.1
            stopped = any(a.reason == "deadman" for a in applied)
            print(f"states={len(states)} moved={moved} deadman={stopped}", flush=True)
            ok = moved and stopped
    finally:
        for p in procs:
            stop_group(p)
        os.unlink(cfg)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
