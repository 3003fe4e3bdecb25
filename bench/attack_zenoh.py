"""``scmbridge bench attack`` rows on who may act over Zenoh (docs/SECURITY.md's attack table): a recorded engage
and estop release replayed, a forger at the station's seq + 1, and a mission published to a station past its goal,
over real Zenoh sessions and routers on free loopback ports; each row's docstring gives its "before".
"""

from __future__ import annotations

import contextlib
import tempfile
import time
import uuid
from pathlib import Path

from bench.attack_rigs import (
    Result,
    _Station,
    _ZenohHost,
    distance_from,
    position,
    until,
)


def replayed_engage_and_release(short: bool) -> Result:
    """Over Zenoh, with a station publishing commands: a person's engage and a person's estop release, recorded off
    the network, replayed after the person handed the robot back / latched the estop again; the same requests
    stamped a minute ago; and old-format ones (no time, no nonce). bridge/core/acts.ActGuard takes a request fresh
    and once. before (``ActGuard.check`` off, --short, two runs): the replayed, the stale and the old-format release
    each released the latch and each engage engaged; 34 and 32 ticks drove, 0.151 and 0.152 m."""
    from bridge.core import wire as M
    from bridge.core.acts import stamped

    out: dict = {}
    with _ZenohHost() as rig, _Station(rig, 0.3):
        def to():  # the host's address, as its answers give it to the person's tool
            return rig.host.acts.address(time.monotonic())

        engage = M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), to()))  # recorded
        ans = rig.engage(engage)
        first = {"engage_engaged": bool(ans and ans.engaged)}  # the recording is potent
        release = M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"), to()))
        rig.attacker.put(rig.keys.estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="attack")))
        until(lambda: rig.host.gate.estopped, 2.0)
        rig.attacker.put(rig.keys.estop, release)  # the person's release, recorded off the network
        first["release_released"] = until(lambda: not rig.host.gate.estopped, 2.0)
        # the person hands the robot back and latches the estop: the robot is parked
        rig.engage(M.encode(M.EngageRequest(stamp=1.0, engaged=False, source="operator")))
        rig.attacker.put(rig.keys.estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="parked")))
        until(lambda: rig.host.gate.estopped, 2.0)
        start, t0 = position(rig.vehicle), time.monotonic()
        stale = dict(stamp=1.0, target=rig.host.acts.epoch, echo=max(1e-3, time.monotonic() - 60.0))
        for kind, rel, eng in (
                ("replayed", release, engage),
                ("stale", M.encode(M.Estop(engaged=False, source="operator", nonce=M.new_nonce(), **stale)),
                 M.encode(M.EngageRequest(source="operator", nonce=M.new_nonce(), **stale))),
                ("unstamped", M.encode(M.Estop(stamp=1.0, engaged=False, source="operator")),
                 M.encode(M.EngageRequest(stamp=1.0, source="operator")))):
            rig.attacker.put(rig.keys.estop, rel)
            time.sleep(0.1)
            ans = rig.engage(eng)
            out[kind] = {"released": not rig.host.gate.estopped, "engaged": bool(ans and ans.engaged)}
        time.sleep(0.3 if short else 1.0)
        moved = distance_from(rig.vehicle, start)
        driven = sum(a.v != 0.0 for a in rig.since(t0))
        refused = {k: v for k, v in rig.host.inputs.snapshot().items() if "refused" in k and v}
        # the control: the person's own tool (fresh, a new nonce) releases and engages, and the station drives
        rig.attacker.put(rig.keys.estop, M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"),
                                                          to())))
        until(lambda: not rig.host.gate.estopped, 2.0)
        ans = rig.engage(M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), to())))
        t1 = time.monotonic()
        control = bool(ans and ans.engaged) and until(lambda: any(a.v != 0.0 for a in rig.since(t1)), 2.0)
    took = any(r["released"] or r["engaged"] for r in out.values())
    return {"reached_vehicle": {"distance_m": moved, "ticks_driven": driven, **out}, "learned": None,
            "refused": refused, "when_first_sent": first, "control_drives": control,
            "ok": not took and moved < 0.01 and driven == 0 and all(first.values()) and control}


def forger_at_seq_plus_one(short: bool) -> Result:
    """Over Zenoh, while the station drives the engaged robot at 0.2 m/s: a forger hears each command and publishes
    a copy at seq + 1 (the station's epoch) with v = 0.45, 1 ms after it. The real command then comes at a seq
    already taken with other content: two senders on one epoch, a conflict that stops the robot while it lasts.
    before (the gate's conflict check off, --short, two runs): 50 of 50 and 49 of 49 ticks applied the forger's
    0.45 m/s; status ok."""
    import threading

    from bridge.core import wire as M
    from bridge.core.acts import stamped

    with _ZenohHost() as rig, _Station(rig, 0.2):
        rig.engage(M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"),
                                    rig.host.acts.address(time.monotonic()))))
        drove = until(lambda: any(a.v == 0.2 for a in rig.since(0.0)), 3.0)  # the station drives it
        sent = [0]
        stop = threading.Event()
        with rig.client() as s:
            pub = s.declare_publisher(rig.keys.cmd)

            def on_cmd(sample) -> None:
                c = M.decode(sample.payload.to_bytes(), M.Command)
                if stop.is_set() or c.v == 0.45:
                    return
                pub.put(M.encode(M.Command(stamp=c.stamp + 0.001, seq=c.seq + 1, v=0.45, omega=0.5, method=c.method,
                                           sender=c.sender, epoch=c.epoch)))
                sent[0] += 1

            sub = s.declare_subscriber(rig.keys.cmd, on_cmd)
            t0 = time.monotonic()
            until(lambda: sent[0] > 0, 2.0)
            time.sleep(1.0 if short else 3.0)
            stop.set()
            sub.undeclare()
        during = rig.since(t0 + 0.2)  # from a few ticks after the first forgery
        status = rig.host.status(time.monotonic())
    forged = sum(a.v == 0.45 for a in during)
    return {"reached_vehicle": {"ticks": len(during), "forged_applied": forged,
                                "stopped_for_conflict": sum(a.reason == "conflict" for a in during)},
            "learned": None, "forged_sent": sent[0], "station_drove_first": drove,
            "status": {"ok": status.ok, "reason": status.reason}, "ok": forged == 0 and len(during) > 10 and sent[0] > 5
            and drove}


def mission_after_goal(short: bool) -> Result:
    """A real station (bridge/nodes/station.py, its loop on a client session of a router on a free port) whose
    mission reached its goal ("finished"); an attacker's session publishes a MissionSpec on ``scm/<robot>/mission``
    (anyone may on the loopback default) and asks the station's ``control`` for its phase: the new mission must
    load idle, and only a person's start drives. before (791b027's ``MissionControl.replace``: a finished mission
    goes on with the new goal; two runs): phase "running" both times: the station drives with no person's act."""
    import threading

    from bridge.core import wire as M
    from bridge.core.config import StationConfig, load_mission, load_mission_spec
    from bridge.nodes.mission_control import MissionControl
    from bridge.nodes.station import Station
    from bridge.nodes.zsession import free_port, make_config, open_session, tcp

    robot, port = f"atk{uuid.uuid4().hex[:8]}", free_port()
    stop = threading.Event()
    with contextlib.ExitStack() as stack:
        d = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
        station = Station(StationConfig(), robot, 10.0, d / "pairs.bin", load_mission(),
                          control=MissionControl(robot, load_mission_spec(), "finished"))
        stack.callback(station.persist)  # (closes its writer thread; the save goes to the temporary directory)
        session = stack.enter_context(open_session(make_config(mode="client", connect=[tcp(port)])))
        loop = threading.Thread(target=station.serve, args=(session, stop, None, False, False), name="attack-station",
                                daemon=True)
        loop.start()
        stack.callback(loop.join, 10.0)
        stack.callback(stop.set)
        until(lambda: station.rx.looping, 10.0)
        attacker = stack.enter_context(open_session(make_config(mode="client", connect=[tcp(port)])))

        def ask() -> M.MissionState | None:
            for reply in attacker.get(M.key(robot, "control"), timeout=5.0,
                                      payload=M.encode(M.MissionRequest(stamp=1.0, action="status"))):
                if reply.ok is not None:
                    return M.decode(reply.ok.payload.to_bytes(), M.MissionState)
            return None

        first = ask()
        attacker.put(M.key(robot, "mission"), M.encode(M.MissionSpec(name="attacker", path=[[0.0, 0.0], [2.0, 0.0]])))
        after, t_end = None, time.monotonic() + (2.0 if short else 5.0)
        while time.monotonic() < t_end:  # until the station has taken it (its next tick)
            after = ask()
            if after is not None and after.mission == "attacker":
                break
            time.sleep(0.05)
        taken = after is not None and after.mission == "attacker"
    phase = after.phase if after is not None else "no answer"
    return {"reached_vehicle": {"phase": phase, "station_drives": phase == "running"}, "learned": None,
            "phase_before": first.phase if first is not None else "no answer", "mission_taken": taken,
            "said": (after.reason if after is not None else "")[:120],
            "ok": taken and phase == "idle" and first is not None and first.phase == "finished"}
