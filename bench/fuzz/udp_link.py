"""The UDP shim's inputs: datagrams at the UDP driver and at the emulated UDP robot, from the pinned peer and from a
stranger, each counted once; afterwards the link must still drive."""

from __future__ import annotations

import math
import random
import socket
import time
from contextlib import ExitStack
from pathlib import Path

import msgspec

from bench.fuzz.harness import (
    LOCAL,
    Crashes,
    Tally,
    VehicleSpy,
    answering,
    drain,
    drive_link,
    new_vehicle,
    result,
    udp_socket,
    wait_until,
)
from bench.fuzz.messages import COMMAND, STATE, CommandStream, MsgMutator, StateStream, wire_ok
from bridge.core import wire as M
from bridge.nodes.node import rss_mb


def _udp_burst(mut: MsgMutator, rng: random.Random, tally: Tally, kind: type, peer: socket.socket,
               stranger: socket.socket, to: tuple, size: int) -> tuple[int, int]:
    """Send ``size`` mutated payloads to ``to``: 15 % from ``stranger`` (foreign, never judged), the rest from the
    pinned ``peer``, each judged by the wire contract for ``kind`` and tallied. Returns (foreign, refused)."""
    foreign = refused_n = 0
    for _ in range(size):
        mk, data = mut.next()
        if rng.random() < 0.15:
            stranger.sendto(data, to)
            foreign += 1
        else:
            peer.sendto(data, to)
            refused = not wire_ok(data, kind)
            tally.add(mk, refused)
            refused_n += refused
    return foreign, refused_n


def udp_driver(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Datagrams at the UDP driver: from its pinned robot address (a socket bound here) and from a stranger. Every
    datagram is counted once: foreign, malformed, a pose, or one of the stream's refusals. Afterwards an emulated
    robot takes the pinned address and the driver drives it."""
    from drivers import open_driver
    from drivers.udp import UdpLinkConfig
    from sim_learner.udp_robot import UdpRobot

    rng = random.Random(seed)
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        fake, stranger = udp_socket(), udp_socket()
        stack.callback(fake.close)
        stack.callback(stranger.close)
        robot_port = fake.getsockname()[1]
        driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=robot_port, bind_port=0,
                                                  state_timeout_s=0.3, open_timeout=5.0))
        stack.callback(driver.close)
        stream = StateStream(rng)

        def hello() -> bytes:
            msg = stream()
            stream.commit()
            return msgspec.msgpack.encode(msg)

        with answering(fake, lambda _data: hello()) as peer:
            driver.open(time.monotonic())
        addr = peer["addr"]
        rss0 = rss_mb()
        h0 = driver.health(time.monotonic())
        base = (h0.frames_received, h0.malformed, h0.detail)
        mut = MsgMutator(rng, STATE, stream, max_blob=1400)
        tally = Tally()
        sent = foreign = bad = 0
        poses = []
        refusals = ("state_out_of_order", "state_seq_jump", "state_old_epoch", "state_foreign_epoch")
        while sent < n:  # bursts the driver's socket buffer holds (it has the kernel's default size)
            size = min(64, n - sent)
            f, b = _udp_burst(mut, rng, tally, M.LearnerState, fake, stranger, addr, size)
            sent, foreign, bad = sent + size, foreign + f, bad + b
            t_end = time.monotonic() + 5.0
            while time.monotonic() < t_end:
                try:
                    poses += driver.poll(time.monotonic())
                except Exception as exc:  # a crash of the receiver, counted
                    crashes.caught("poll", exc)
                    break
                if driver.health(time.monotonic()).frames_received - base[0] >= sent:
                    break
                time.sleep(0.001)
            driver.send(0.2, 0.1, time.monotonic())
        h = driver.health(time.monotonic())
        d = h.detail
        got = {"frames": h.frames_received - base[0], "malformed": h.malformed - base[1],
               "foreign": d.foreign - base[2].foreign, "poses": len(poses),
               "refused": sum(getattr(d, k) - getattr(base[2], k) for k in refusals)}
        want = {"frames": sent, "malformed": bad, "foreign": foreign, "poses+refused": sent - foreign - bad}
        exact = (got["frames"] == sent and got["malformed"] == bad and got["foreign"] == foreign
                 and got["poses"] + got["refused"] == want["poses+refused"])
        nonfinite = sum(not all(math.isfinite(a) for a in (p.x, p.y, p.theta, p.v or 0.0, p.omega or 0.0))
                        for p in poses)
        # what the driver sent its robot meanwhile: only what it was told (or stops), finite
        cmds = [M.decode(b, M.Command) for b, src in drain(fake) if src[:2] == addr[:2]]
        wrong = sum((c.v, c.omega) not in ((0.2, 0.1), (0.0, 0.0)) for c in cmds)
        rss1 = rss_mb()
        # a real robot on the pinned address (the fuzzed stream has gone silent): it must be driven
        fake.close()
        vehicle = new_vehicle()
        spy = VehicleSpy(vehicle, 1.0, 2.0)
        robot = UdpRobot(vehicle, port=robot_port, peer=addr[:2], watchdog=0.3).start()
        stack.callback(robot.stop)
        drive = drive_link(driver, spy, 0.25, crashes)
    return result(sent, got["malformed"], bad, exact, crashes, t0, (rss0, rss1), "bench (driver in-process)",
                   got=got, want=want, contract_violations=tally.contract_violations(),
                   kinds_sent_refused=tally.report(), nonfinite_poses=nonfinite,
                   vehicle={"commands_to_robot": len(cmds), "not_as_told": wrong, "ok": wrong == 0},
                   drives_after=drive)


def udp_robot(n: int, seed: int, workdir: Path | None = None) -> dict:
    """Datagrams at the emulated UDP robot: from its pinned peer (a socket bound here) and from a stranger. Every
    datagram is counted once (``received`` = foreign + malformed + a stream refusal + over its limits + applied);
    the vehicle never gets a non-finite command or one beyond the robot's own limits. Afterwards a real driver takes
    the peer's address and drives it."""
    from drivers import open_driver
    from drivers.udp import UdpLinkConfig
    from sim_learner.udp_robot import UdpRobot

    rng = random.Random(seed)
    t0, rss0, crashes = time.monotonic(), rss_mb(), Crashes()
    with crashes, ExitStack() as stack:
        peer, stranger = udp_socket(), udp_socket()
        stack.callback(peer.close)
        stack.callback(stranger.close)
        vehicle = new_vehicle()
        spy = VehicleSpy(vehicle, 1.0, 2.0)
        robot = UdpRobot(vehicle, peer=peer.getsockname(), watchdog=0.3, v_max=1.0, omega_max=2.0).start()
        stack.callback(robot.stop)
        to = (LOCAL, robot.port)
        rss0 = rss_mb()
        c0 = dict(robot.counters)
        mut = MsgMutator(rng, COMMAND, CommandStream(rng, "driver", (3.0, 5.0)), max_blob=1400)
        tally = Tally()
        sent = foreign = bad = 0
        while sent < n:  # a burst the robot's socket holds even if its thread does not run meanwhile (a loaded
            size = min(48, n - sent)  # machine): 128 of up to 1.4 KB overflowed the kernel's buffer
            f, b = _udp_burst(mut, rng, tally, M.Command, peer, stranger, to, size)
            sent, foreign, bad = sent + size, foreign + f, bad + b
            if not wait_until(lambda s=sent: robot.counters["received"] - c0["received"] >= s, 5.0, 0.001):
                break
        c = {k: v - c0[k] for k, v in robot.counters.items()}
        verdicts = ("applied", "out_of_order", "seq_jump", "old_epoch", "foreign_epoch", "over_limits")
        exact = (c["received"] == sent and c["foreign"] == foreign and c["malformed"] == bad
                 and sum(c[k] for k in verdicts) == sent - foreign - bad)
        rss1 = rss_mb()
        peer_port = peer.getsockname()[1]
        peer.close()
        driver = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=robot.port, bind_port=peer_port,
                                                  open_timeout=5.0))
        stack.callback(driver.close)
        try:
            driver.open(time.monotonic())
            drive = drive_link(driver, spy, 0.25, crashes)
        except Exception as exc:
            crashes.caught("driver open", exc)
            drive = {"ok": False}
    return result(sent, c["malformed"], bad, exact, crashes, t0, (rss0, rss1), "bench (robot in-process)",
                   counters={k: c[k] for k in ("received", "foreign", "malformed", *verdicts)},
                   contract_violations=tally.contract_violations(), kinds_sent_refused=tally.report(),
                   vehicle={**spy.report(), "ok": spy.ok}, drives_after=drive)
