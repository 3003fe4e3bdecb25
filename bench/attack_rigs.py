"""The rigs ``scmbridge bench attack``'s rows share (bench/attack*.py): a man in the middle on
loopback UDP (:class:`Tap`), the emulated UDP robot and the real UDP driver through it, real DriverHosts on real state
directories driven in this process (:class:`_LatchRig`) or serving over real Zenoh sessions (:class:`_ZenohHost`),
a station-like command sender (:class:`_Station`), and bounded waits."""

from __future__ import annotations

import contextlib
import math
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

Result = dict


class Tap:
    """A man in the middle on 127.0.0.1: one UDP socket the driver takes for the robot and the robot for its peer;
    forwards both ways, records what the driver sends (unless ``hold``: then it records and keeps it back). A replay
    leaves from that socket, the very address the robot obeys (tests/integration/test_udp_replay.py uses it too)."""

    def __init__(self, driver_port: int) -> None:
        import socket
        import threading

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        self.addr = self.sock.getsockname()
        self.driver = ("127.0.0.1", driver_port)
        self.robot: tuple[str, int] | None = None
        self.recorded: list[tuple[float, bytes]] = []
        self.hold = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="attack-tap", daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, src = self.sock.recvfrom(65536)
            except OSError:  # (a timeout is one)
                continue
            if src == self.driver:
                self.recorded.append((time.monotonic(), data))
                if not self.hold and self.robot is not None:
                    self.sock.sendto(data, self.robot)
            elif src == self.robot:
                self.sock.sendto(data, self.driver)

    def replay(self, datagrams: list[tuple[float, bytes]], paced: bool = True) -> None:
        """``datagrams`` to the robot from the tap (the address it obeys), at their recorded pace."""
        assert self.robot is not None
        t0, r0 = time.monotonic(), datagrams[0][0] if datagrams else 0.0
        for t, data in datagrams:
            if paced:
                time.sleep(max(0.0, (t - r0) - (time.monotonic() - t0)))
            self.sock.sendto(data, self.robot)

    def __enter__(self) -> Tap:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.sock.close()


def udp_robot(key: bytes | None, peer: tuple[str, int], port: int = 0):
    """The emulated UDP robot (keyed with ``key``, obeying ``peer``) started on ``port`` (0: a free one), and the
    simulated vehicle it drives."""
    from sim_learner.dynamics import mpc_learner
    from sim_learner.udp_robot import UdpRobot
    from sim_learner.vehicle import SimVehicle

    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    return UdpRobot(vehicle, port=port, peer=peer, key=key, watchdog=0.3).start(), vehicle


def distance_from(vehicle, start: tuple[float, float]) -> float:
    """How far ``vehicle`` is now from ``start``, m (rounded to the millimetre)."""
    body = vehicle.advance(time.monotonic())
    return round(math.hypot(body.x - start[0], body.y - start[1]), 3)


def position(vehicle) -> tuple[float, float]:
    """Where ``vehicle`` is now (x, y)."""
    body = vehicle.advance(time.monotonic())
    return body.x, body.y


def drive_udp(driver, seconds: float, v: float) -> None:
    """The real UDP driver sends (v, 0) every 20 ms for ``seconds`` and reads what the robot says."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        driver.send(v, 0.0, time.monotonic())
        driver.poll(time.monotonic())
        time.sleep(0.02)


@contextlib.contextmanager
def tapped_driver(key_file: Path, tap: Tap) -> Iterator:
    """The real UDP driver keyed with ``key_file``, talking to the robot through ``tap`` (from the port the tap takes
    for the driver), open; closed on exit."""
    from drivers import open_driver
    from drivers.udp import UdpLinkConfig

    driver = open_driver("udp", UdpLinkConfig(robot_port=tap.addr[1], bind_port=tap.driver[1],
                                              key_file=str(key_file), open_timeout=5.0))
    try:
        driver.open(time.monotonic())
        yield driver
    finally:
        driver.close()


def until(pred: Callable[[], bool], timeout: float, step: Callable[[], object] | None = None) -> bool:
    """Whether ``pred()`` holds within ``timeout`` s, calling ``step()`` (a poll) before each look."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if step is not None:
            step()
        if pred():
            return True
        time.sleep(0.01)
    return pred()


class _NullPub:
    """Where the in-process host's applied, state and status go (these rows judge the vehicle, not the messages)."""

    def put(self, data: bytes) -> None:
        pass


class _LatchRig:
    """The emulated UDP robot on loopback and real DriverHosts for it, each a start of the host on a real state
    directory (a restart is a new DriverHost on the same directory), driven in this process."""

    def __init__(self) -> None:
        from bridge.tools.procs import free_udp_port
        from drivers.udp import UdpLinkConfig

        bind = free_udp_port()
        self.device, self.vehicle = udp_robot(None, ("127.0.0.1", bind))
        self.link_cfg = UdpLinkConfig(insecure=True, robot_port=self.device.port, bind_port=bind)
        self.hosts: list = []

    def host(self, latch: Path, saver: Callable[[Path, bytes], None] | None = None):
        from bridge.core.paths import save_atomic
        from bridge.nodes.driver_config import load_driver
        from bridge.nodes.driver_host import DriverHost
        from drivers import open_driver

        cfg = load_driver(None)
        host = DriverHost(cfg, "udp", open_driver("udp", self.link_cfg), "r1", cfg.driver.rate_hz, latch_path=latch,
                          latch_saver=saver or save_atomic)
        host.pubs = {k: _NullPub() for k in ("applied", "state", "status")}
        host.driver.open(time.monotonic())
        self.hosts.append(host)
        return host

    def stop(self, host) -> None:
        host.driver.close(disarm=False, stop_timeout=0.0)
        host.latch.close(5.0)
        self.hosts.remove(host)

    def estop(self, host, engaged: bool = True) -> None:
        """An operator's estop (or release, as the person's tool sends it: fresh, with its nonce), waited until
        saved or failed."""
        import threading

        from bridge.core import wire as M
        from bridge.core.acts import stamped

        host.on_estop(stamped(M.Estop(stamp=time.monotonic(), engaged=engaged, source="operator", reason="attack"),
                              host.acts.address(time.monotonic())), time.monotonic())
        done = threading.Event()
        if host.latch.defer(done.set):
            done.wait(5.0)

    def engage_and_drive(self, host, seconds: float) -> dict:
        """Someone engages (a fresh request: the attack is on the disk, not on the request) and a station drives at
        0.3 m/s for ``seconds``: what the robot did."""
        from bridge.core import wire as M
        from bridge.core.acts import stamped

        ans = host.handle_engage(stamped(M.EngageRequest(stamp=time.monotonic(), source="operator")), time.monotonic())
        start, epoch, seq = position(self.vehicle), M.new_epoch(), 0
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            seq += 1
            now = time.monotonic()
            host.on_cmd(M.Command(stamp=now, seq=seq, v=0.3, omega=0.0, method="scm", epoch=epoch), now)
            host.tick(now)
            time.sleep(0.02)
        host.tick(time.monotonic())
        return {"engaged": ans.engaged, "distance_m": distance_from(self.vehicle, start), "latched": host.gate.estopped,
                "latched_by": host.gate.estop_source}

    def control(self, host, seconds: float) -> float:
        """The control: the person releases the estop (saved, signed) and the host engages and drives, so a row's
        "0.0 m" is the latch's doing, not a rig that cannot drive; the metres driven."""
        self.estop(host, engaged=False)
        return self.engage_and_drive(host, seconds)["distance_m"]

    def __enter__(self) -> _LatchRig:
        return self

    def __exit__(self, *exc: object) -> None:
        for host in list(self.hosts):
            self.stop(host)
        self.device.stop()


class _ZenohHost:
    """A router session on a free loopback port; a real DriverHost for the emulated UDP robot serving on a client
    session of it (its own thread, as ``scmbridge driver`` runs); a state directory of its own; the attacker's
    client session; a subscriber counting what the host applied."""

    def __enter__(self) -> _ZenohHost:
        import threading

        from bridge.core import wire as M
        from bridge.nodes.driver_config import load_driver
        from bridge.nodes.driver_host import DriverHost
        from bridge.nodes.zsession import free_port, make_config, open_session, tcp
        from bridge.tools.procs import free_udp_port
        from drivers import open_driver
        from drivers.udp import UdpLinkConfig

        self.robot = f"atk{uuid.uuid4().hex[:8]}"
        self.keys = M.Keys(self.robot)
        self.lock = threading.Lock()
        self.applied: list = []
        self.stop = threading.Event()
        self.stack = contextlib.ExitStack()  # everything started, closed in reverse (also when a start fails)
        try:
            state = Path(self.stack.enter_context(tempfile.TemporaryDirectory()))
            self.port = port = free_port()
            self.router = self.stack.enter_context(open_session(make_config(mode="router", listen=[tcp(port)])))
            self.client = lambda: open_session(make_config(mode="client", connect=[tcp(port)]))
            bind = free_udp_port()
            self.device, self.vehicle = udp_robot(None, ("127.0.0.1", bind))
            self.stack.callback(self.device.stop)
            self.sub = self.router.declare_subscriber(self.keys.applied, self._on_applied)
            self.stack.callback(self.sub.undeclare)
            cfg = load_driver(None)
            link = open_driver("udp", UdpLinkConfig(insecure=True, robot_port=self.device.port, bind_port=bind))
            self.host = DriverHost(cfg, "udp", link, self.robot, cfg.driver.rate_hz, latch_path=state / "estop.bin")
            self.host_session = host_session = self.stack.enter_context(self.client())
            self.thread = threading.Thread(target=self.host.serve, args=(host_session, self.stop, None),
                                           name="attack-driver-host", daemon=True)
            self.thread.start()
            self.stack.callback(self._stop_host)
            until(lambda: self.host.timing.ticker is not None, 10.0)
            self.attacker = self.stack.enter_context(self.client())
        except BaseException:
            self.stack.close()
            raise
        return self

    def _stop_host(self) -> None:
        self.stop.set()
        self.thread.join(timeout=10.0)
        self.host.close()

    def _on_applied(self, sample) -> None:
        from bridge.core import wire as M

        a = M.decode(sample.payload.to_bytes(), M.Applied)
        with self.lock:
            self.applied.append((time.monotonic(), a))

    def since(self, t0: float) -> list:
        with self.lock:
            return [a for t, a in self.applied if t > t0]

    def engage(self, payload: bytes):
        """One query on the engage key (sent once: a retry would not be a replay): the host's answer."""
        from bridge.core import wire as M

        for reply in self.attacker.get(self.keys.engage, payload=payload, timeout=5.0):
            if reply.ok is not None:
                return M.decode(reply.ok.payload.to_bytes(), M.EngageState)
        return None

    def __exit__(self, *exc: object) -> None:
        self.stack.close()


class _Station:
    """A station-like sender on its own client session: one epoch, commands (v, 0) at 20 Hz; optionally a forger
    beside it that copies each command at seq + 1 with other velocities (the epoch is readable off the network)."""

    def __init__(self, rig: _ZenohHost, v: float) -> None:
        import threading

        self.rig, self.v = rig, v
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="attack-station", daemon=True)

    def _run(self) -> None:
        from bridge.core import wire as M

        with self.rig.client() as s:
            pub = s.declare_publisher(self.rig.keys.cmd)
            epoch, seq = M.new_epoch(), 0
            while not self.stop.wait(0.05):
                seq += 1
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=self.v, omega=0.0, method="scm",
                                           sender="station", epoch=epoch)))

    def __enter__(self) -> _Station:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(timeout=5.0)
