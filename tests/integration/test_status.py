"""``scmbridge status`` over real Zenoh: one line per robot and node naming the one reason a robot is not driving,
and an exit status a script can use."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp


def _publisher(session, stop: threading.Event, statuses: dict[tuple[str, str], M.Status]) -> None:
    pubs = {k: session.declare_publisher(M.status_key(*k)) for k in statuses}
    seq = 0
    while not stop.is_set():
        for k, st in statuses.items():
            pubs[k].put(M.encode(M.Status(**{**{f: getattr(st, f) for f in st.__struct_fields__},
                                              "stamp": time.monotonic(), "seq": seq})))
        seq += 1
        stop.wait(0.2)


def _status(port: int, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", "status", *args, "--mode", "client", "--connect",
                           tcp(port), "--timeout", "1.0"], capture_output=True, text=True, timeout=60)


def test_status_names_the_reason_each_robot_is_not_driving() -> None:
    port = free_port()
    statuses = {
        ("rover1", "station"): M.Status(stamp=0, seq=0, node="station", ok=True, state="driving", text="driving",
                                        progress=0.42, counters={"refined_pairs": 17}, changed_cells=[115, 116]),
        ("rover1", "driver"): M.Status(stamp=0, seq=0, node="driver", ok=True, state="driving",
                                       text="link can: driving (cmd)", latencies_ms={"telemetry_age": 20.0}),
        ("rover2", "station"): M.Status(stamp=0, seq=0, node="station", ok=False, state="paused",
                                        text="paused: estop latched by operator", progress=0.1),
        ("rover2", "driver"): M.Status(stamp=0, seq=0, node="driver", ok=False, state="estop",
                                       text="link udp: estop latched by operator"),
    }
    stop = threading.Event()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session:
        t = threading.Thread(target=_publisher, args=(session, stop, statuses), daemon=True)
        t.start()
        try:
            every = _status(port, "--all")
            one = _status(port, "--robot", "rover1")
            ghost = _status(port, "--robot", "ghost")
        finally:
            stop.set()
            t.join(2)
    lines = every.stdout.strip().splitlines()
    assert every.returncode == 1, every
    assert len(lines) == 4 and [ln.split()[:3] for ln in lines] == [
        ["rover1", "station", "driving"], ["rover1", "driver", "driving"],
        ["rover2", "station", "paused"], ["rover2", "driver", "estop"]], lines
    assert "mission 42%" in lines[0] and "pairs 17" in lines[0] and "pose 0.02 s old" in lines[1]
    assert "re-learned cells 115, 116" in lines[0]  # the cells whose learner changed ([transfer] adapt)
    assert "estop latched by operator" in lines[2] and "estop latched by operator" in lines[3]
    assert one.returncode == 0 and len(one.stdout.strip().splitlines()) == 2, one
    assert ghost.returncode == 2 and "no node's status arrived" in ghost.stderr and "Traceback" not in ghost.stderr


def test_a_service_waits_for_the_router_and_a_tool_says_it_is_not_there_in_one_line() -> None:
    import threading as th

    from bridge.nodes.zsession import open_session

    port = free_port()
    stop, out = th.Event(), {}

    def service() -> None:
        s = open_session(make_config(mode="client", connect=[tcp(port)]), wait=stop, what="test service")
        out["zid"] = str(s.info.zid())
        out["routers"] = s.info.routers_zid()
        s.close()

    t = th.Thread(target=service, daemon=True)
    t.start()
    time.sleep(0.6)  # absence: the router is not up yet, the service waits, it does not exit
    assert t.is_alive() and not out
    with open_session(make_config(mode="router", listen=[tcp(port)])):
        t.join(10)
        assert not t.is_alive() and out.get("routers"), out
    res = subprocess.run([sys.executable, "-m", "bridge", "estop", "--robot", "r1", "--mode", "client", "--connect",
                          tcp(port)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "cannot reach the Zenoh router" in res.stderr and "Traceback" not in res.stderr


def test_status_asks_the_nodes_and_does_not_wait_for_their_next_status() -> None:
    """Finding: `status` took 1.7-1.9 s a call, listening a fixed 1.5 s for the periodic statuses. Each node's status
    key answers a query with its last status (:class:`bridge.nodes.node.StatusOut`, what the station and the driver
    host publish through): nodes that publish only once here are still read at once, long before ``--timeout``."""
    from bridge.nodes.node import StatusOut

    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session:
        outs = {n: StatusOut(session, M.status_key("rover7", n)) for n in ("station", "driver")}
        outs["station"].put(M.encode(M.Status(stamp=time.monotonic(), seq=0, node="station", ok=True,
                                              state="driving", reason="ok", text="driving")))
        outs["driver"].put(M.encode(M.Status(stamp=time.monotonic(), seq=0, node="driver", ok=True, state="driving",
                                             reason="ok", text="link can: driving (cmd)")))
        res = subprocess.run([sys.executable, "-m", "bridge", "status", "--robot", "rover7", "--mode", "client",
                              "--connect", tcp(port), "--timeout", "600"], capture_output=True, text=True,
                             timeout=120)
        every = subprocess.run([sys.executable, "-m", "bridge", "status", "--all", "--mode", "client", "--connect",
                                tcp(port), "--timeout", "600"], capture_output=True, text=True, timeout=120)
    for r in (res, every):
        rows = [ln.split()[:2] for ln in r.stdout.splitlines()]
        assert r.returncode == 0 and rows == [["rover7", "station"], ["rover7", "driver"]], r.stdout + r.stderr


def test_a_status_that_hears_nothing_names_the_endpoints_of_its_zenoh_config(tmp_path) -> None:
    """Finding: `status --timeout 0.5 --zenoh-config FILE` said it tried "the Zenoh defaults"."""
    port = free_port()
    conf = tmp_path / "client.json5"
    conf.write_text(f'{{ mode: "client", connect: {{ endpoints: ["{tcp(port)}"] }}, '
                    'scouting: { multicast: { enabled: false } } }')
    with open_session(make_config(mode="router", listen=[tcp(port)])):
        res = subprocess.run([sys.executable, "-m", "bridge", "status", "--all", "--zenoh-config", str(conf),
                              "--timeout", "0.5"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "Zenoh defaults" not in res.stderr, res.stderr
    assert str(conf) in res.stderr, res.stderr


def test_the_driver_line_says_moving_or_stopped_from_the_measured_speed_never_driving_for_a_stopped_robot() -> None:
    """Finding: `driving   link can: driving (deadman)` for a robot standing still after its station died. The
    driver host's line says what the vehicle does, measured, beside engaged or not and the host's reason."""
    from bridge.tools.status import Seen
    from bridge.tools.status import report as status_report

    def driver(measured, engaged: bool, text: str, state: str = "driving") -> M.Status:
        return M.Status(stamp=0, seq=0, node="driver", ok=True, state=state, reason="ok", text=text,
                        measured=measured, engaged=engaged)

    station = M.Status(stamp=0, seq=0, node="station", ok=True, state="driving", reason="ok", text="driving")
    cases = [(driver([0.0, 0.0], True, "link can: holding a stop: no fresh command (deadman)"), "stopped"),
             (driver([0.21, -0.1], True, "link can: applying the station's commands (cmd)"), "moving"),
             (driver([0.0, 0.3], True, "link can: applying the station's commands (cmd)"), "moving"),  # turning
             (driver([0.0, 0.0], False, "link can: estop latched by operator", "estop"), "stopped")]
    for st, word in cases:
        seen = Seen()
        seen.latest = {("r1", "station"): (station, time.monotonic()), ("r1", "driver"): (st, time.monotonic())}
        lines, _ = status_report(seen, ["r1"])
        row = lines[1].split()
        assert row[:3] == ["r1", "driver", word] and "driving" not in lines[1], lines[1]
        assert ("| not engaged |" in lines[1]) == (not st.engaged) and "m/s" in lines[1], lines[1]
