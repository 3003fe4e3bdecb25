"""ArduPilot's real Rover firmware in software-in-the-loop (SITL), as a learner the MAVLink link drives.

The emulated rover (:mod:`sim_learner.mavlink_rover`) is written from ArduPilot's source; this runs the source
itself: the same modes, arming checks, GUIDED timeouts, MAVLink 2 signing and speed / turn-rate controllers, with a
simulated body (docs/ARCHITECTURE.md §6-7: the MAVLink link and the person in charge). :class:`Sitl` starts one
``ardurover`` process and :class:`Pilot` is the ground station on its first serial port, doing what a person at a
ground station does (mode, arming, parameters, the signing key) and watching what the vehicle reports.

One SITL process, as ``sim_vehicle.py`` would start it (its README in the shared SITL directory says the same):

* its own temporary working directory (it writes ``eeprom.bin`` and logs there) and ``-w`` (start from defaults);
* its own instance ``-I N``: every port moves by ``10 * N`` (TCP 5760 SERIAL0 the ground station, 5762 SERIAL1,
  5763 SERIAL2; UDP 5501 RC input); N is chosen so that those ports are free right now, never a fixed one;
* ``--defaults`` the model's upstream parameter files (``rover.parm`` + ``<model>.parm``), plus any extra ``.parm``;
* a fast boot (``--speedup``, 10 by default) until the EKF has a position (LOCAL_POSITION_NED flows and
  EKF_STATUS_REPORT says it has an absolute horizontal position), then real time (``SIM_SPEEDUP 1``, its PARAM_VALUE
  read back): a driver host's clocks and deadlines are real time.

SITL does not boot until a ground station connects to SERIAL0 (and always accepts unsigned MAVLink there), so the
pilot connects first. The driver host's link is :attr:`Sitl.driver_url` (SERIAL1), a third link
:attr:`Sitl.spare_url` (SERIAL2). Everything is cleaned up on :meth:`Sitl.stop` (the context manager's exit): the
pilot's connection closed, the process group killed with bounded waits, the directory removed.

Where the binary is: ``$SCMBRIDGE_SITL`` (the binary, or a directory holding it), else ``shared/sitl/ardurover`` in
the directory that holds the repository (as CI has it) or one further up; :func:`find_sitl` returns None when there
is none (the tests skip).
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from sim_learner.mavlink_dialect import MAV, mavutil_v2

#: the environment variable naming the SITL binary (or its directory)
ENV = "SCMBRIDGE_SITL"
#: the models SITL's Rover simulates that this wrapper knows the parameter files of
MODELS = ("rover", "rover-skid", "motorboat", "balancebot")
#: the TCP ports of instance 0 (SERIAL0 .. SERIAL2 and the one between) and its UDP RC-input port
TCP_BASE, UDP_RC_BASE = 5760, 5501
#: Rover's mode numbers (Rover/mode.h)
MODES: dict[str, int] = dict(mavutil.mode_mapping_byname(MAV.MAV_TYPE_GROUND_ROVER))
#: EKF_STATUS_REPORT flag: the EKF has an absolute horizontal position (GPS): GUIDED can be armed
EKF_POS_HORIZ_ABS = 16
#: a ground station's component id (Mission Planner's), as the pilot
PILOT_COMPONENT = MAV.MAV_COMP_ID_MISSIONPLANNER
#: MAVLink signing timestamps count 10 us units from 2015-01-01 00:00:00 UTC
SIGNING_EPOCH = 1420070400


class SitlError(RuntimeError):
    """SITL did not do what was asked (did not boot, refused a command, did not answer); the text says what."""


def repo_root() -> Path:
    return Path(__file__).resolve().parents[1]


def find_sitl(env: dict[str, str] | None = None) -> Path | None:
    """The ``ardurover`` binary: ``$SCMBRIDGE_SITL`` (a file, or a directory holding ``ardurover``), else the first
    ``shared/sitl/ardurover`` in a parent of the repository; None when there is none or it is not executable."""
    env = os.environ if env is None else env
    given = env.get(ENV, "")
    if given:
        cands = [Path(given) / "ardurover" if Path(given).is_dir() else Path(given)]
    else:
        cands = [p / "shared" / "sitl" / "ardurover" for p in repo_root().parents]
    for c in cands:
        if c.is_file() and os.access(c, os.X_OK):
            return c
    return None


def where_sitl_is_looked_for() -> str:
    """The places :func:`find_sitl` looks, in words (a skip's reason)."""
    given = os.environ.get(ENV, "")
    return given if given else str(repo_root().parent / "shared" / "sitl" / "ardurover") + " (or further up)"


def ports_of(instance: int) -> tuple[list[int], list[int]]:
    """The TCP and UDP ports SITL instance ``instance`` binds."""
    return [TCP_BASE + 10 * instance + k for k in range(4)], [UDP_RC_BASE + 10 * instance]


def _free(instance: int) -> bool:
    """Every port of the instance can be bound right now (SITL binds them on all addresses: so do we)."""
    tcp, udp = ports_of(instance)
    socks: list[socket.socket] = []
    try:
        for kind, ports in ((socket.SOCK_STREAM, tcp), (socket.SOCK_DGRAM, udp)):
            for p in ports:
                s = socket.socket(socket.AF_INET, kind)
                socks.append(s)
                s.bind(("", p))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()


#: SITL keeps its instance number in 8 bits (-I 313 is instance 57): 1..255, 0 left to a person's own SITL
MAX_INSTANCE = 255


def free_instance(tried: Iterable[int] = ()) -> int:
    """An instance number whose ports are free (1..MAX_INSTANCE), starting from one that depends on this process
    and the time so that parallel test workers try different ones first."""
    skip = set(tried)
    start = (os.getpid() + time.monotonic_ns() // 1000) % MAX_INSTANCE
    for k in range(MAX_INSTANCE):
        n = 1 + (start + k) % MAX_INSTANCE
        if n not in skip and _free(n):
            return n
    raise SitlError(f"no SITL instance with free ports (TCP 5760+10N..5763+10N) for N in 1..{MAX_INSTANCE}")


def signing_timestamp(now: float | None = None) -> int:
    """Now as a MAVLink 2 signing timestamp (10 us units since 2015-01-01 UTC)."""
    return int(((time.time() if now is None else now) - SIGNING_EPOCH) * 100_000)


@dataclass
class Sample:
    """What the pilot saw of the vehicle at one moment (our monotonic clock)."""

    t: float
    armed: bool
    mode: str
    speed: float  # m/s, the horizontal speed of the last LOCAL_POSITION_NED
    x: float  # m north (NED, from the EKF origin)
    y: float  # m east


@dataclass
class _State:
    mode: str = "unknown"
    armed: bool = False
    heartbeats: int = 0
    signed_heartbeats: int = 0
    position: Any = None  # the last LOCAL_POSITION_NED
    position_t: float = -math.inf
    attitude: Any = None
    hud: Any = None
    ekf_flags: int = 0
    params: dict[str, float] = field(default_factory=dict)
    acks: list[tuple[float, int, int]] = field(default_factory=list)  # (t, command, result)
    texts: list[str] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)


class VehicleView:
    """What a person's link sees of the vehicle, read under ``self.cond`` from ``self.s`` (its mode, arming, last
    LOCAL_POSITION_NED and ATTITUDE, the samples kept): shared by :class:`Pilot` (SITL) and the tests' pilot of the
    emulated rover, which fill ``s`` each their own way."""

    cond: threading.Condition
    s: Any

    @staticmethod
    def _speed(p: Any) -> float:
        return math.hypot(p.vx, p.vy) if p is not None else 0.0

    def wait(self, pred: Callable[[_State], bool], timeout: float) -> bool:
        """Wait (on the reader's notifications, not a sleep) until ``pred(state)`` holds; False after ``timeout``."""
        with self.cond:
            return self.cond.wait_for(lambda: pred(self.s), timeout)

    @property
    def mode(self) -> str:
        with self.cond:
            return self.s.mode

    @property
    def armed(self) -> bool:
        with self.cond:
            return self.s.armed

    @property
    def speed(self) -> float:
        """The horizontal speed of the last LOCAL_POSITION_NED, m/s."""
        with self.cond:
            return self._speed(self.s.position)

    @property
    def yaw_rate(self) -> float:
        """ATTITUDE's yawspeed, rad/s, clockwise positive (NED)."""
        with self.cond:
            return float(self.s.attitude.yawspeed) if self.s.attitude is not None else 0.0

    @property
    def position(self) -> tuple[float, float]:
        """(north, east) of the last LOCAL_POSITION_NED, m."""
        with self.cond:
            p = self.s.position
            return (p.x, p.y) if p is not None else (0.0, 0.0)

    def samples(self, since: float = -math.inf) -> list[Sample]:
        with self.cond:
            return [x for x in self.s.samples if x.t >= since]


class Pilot(VehicleView):
    """The ground station on SITL's SERIAL0: a person's link to the vehicle.

    A thread reads every message (keeping the vehicle's mode, arming, position, speed and the answers to our
    commands) and sends a HEARTBEAT each second, as a ground station does. The helpers block until the vehicle says
    it did what was asked (a COMMAND_ACK *and* the HEARTBEAT showing it; a PARAM_VALUE) and raise :class:`SitlError`
    naming what it said or that it said nothing."""

    def __init__(self, url: str, source_system: int = 255, source_component: int = PILOT_COMPONENT) -> None:
        self.url = url
        self.conn = mavutil_v2().mavlink_connection(url, source_system=source_system, source_component=source_component,
                                                    dialect="ardupilotmega", autoreconnect=False, retries=0)
        self.lost = threading.Event()  # the vehicle closed the connection (SITL exited)
        self.conn.handle_eof = self.lost.set  # pymavlink would print and spin on a closed socket
        self.conn.handle_disconnect = self.lost.set
        self.target = (1, 1)
        self.s = _State()
        self.cond = threading.Condition()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sitl-pilot", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------ the link
    def send(self, name: str, *args: Any) -> None:
        """Send message ``name`` (pymavlink's ``<name>_send`` arguments), from any thread."""
        with self._send_lock:
            getattr(self.conn.mav, f"{name}_send")(*args)

    def _run(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set() and not self.lost.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 1.0
                with contextlib.suppress(OSError):
                    self.send("heartbeat", MAV.MAV_TYPE_GCS, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                time.sleep(0.05)
                continue
            if msg is not None:
                self._handle(msg, time.monotonic())
        with self.cond:  # waiters learn at once that nothing more will come
            self.cond.notify_all()

    def _handle(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if msg.get_srcSystem() != self.target[0] or msg.get_srcComponent() != self.target[1]:
            return
        with self.cond:
            s = self.s
            if kind == "HEARTBEAT":
                s.heartbeats += 1
                s.signed_heartbeats += bool(getattr(msg, "_signed", False))
                s.mode = mavutil.mode_mapping_bynumber(MAV.MAV_TYPE_GROUND_ROVER).get(msg.custom_mode,
                                                                                      str(msg.custom_mode))
                s.armed = bool(msg.base_mode & MAV.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "LOCAL_POSITION_NED":
                s.position, s.position_t = msg, now
            elif kind == "ATTITUDE":
                s.attitude = msg
            elif kind == "VFR_HUD":
                s.hud = msg
            elif kind == "EKF_STATUS_REPORT":
                s.ekf_flags = msg.flags
            elif kind == "PARAM_VALUE":
                s.params[msg.param_id] = float(msg.param_value)
            elif kind == "COMMAND_ACK":
                s.acks.append((now, msg.command, msg.result))
            elif kind == "STATUSTEXT":
                s.texts.append(msg.text)
            else:
                return
            if kind in ("HEARTBEAT", "LOCAL_POSITION_NED"):
                p = s.position
                s.samples.append(Sample(now, s.armed, s.mode, self._speed(p), p.x if p else 0.0, p.y if p else 0.0))
            self.cond.notify_all()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        with contextlib.suppress(OSError):
            self.conn.close()

    # ------------------------------------------------------------------------------------------ watching
    def texts(self) -> list[str]:
        with self.cond:
            return list(self.s.texts)

    # ------------------------------------------------------------------------------------------ acting
    def interval(self, msg_id: int, hz: float) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL on this link (each link has its own), acknowledged."""
        self.command(MAV.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def command(self, command: int, *params: float, timeout: float = 3.0) -> None:
        """COMMAND_LONG, sent again each second until its COMMAND_ACK; raises unless MAV_RESULT_ACCEPTED."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        t0 = time.monotonic()
        t_end = t0 + timeout
        while time.monotonic() < t_end:
            self.send("command_long", *self.target, command, 0, *p)
            if self.wait(lambda s: any(t >= t0 and c == command for t, c, _ in s.acks), min(1.0, t_end -
                                                                                            time.monotonic())):
                with self.cond:
                    result = [r for t, c, r in self.s.acks if t >= t0 and c == command][-1]
                if result != MAV.MAV_RESULT_ACCEPTED:
                    name = MAV.enums["MAV_RESULT"][result].name if result in MAV.enums["MAV_RESULT"] else result
                    texts = self.texts()[-3:]
                    raise SitlError(f"command {command} refused: {name}; vehicle said {texts}")
                return
        raise SitlError(f"no COMMAND_ACK for command {command} within {timeout} s")

    def set_mode(self, name: str, timeout: float = 5.0) -> None:
        """The mode ``name`` (GUIDED, HOLD, MANUAL): acknowledged and shown in the vehicle's HEARTBEAT."""
        self.command(MAV.MAV_CMD_DO_SET_MODE, MAV.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODES[name], timeout=timeout)
        if not self.wait(lambda s: s.mode == name, timeout):
            raise SitlError(f"mode {name} acknowledged but the HEARTBEAT says {self.mode}")

    def arm(self, armed: bool = True, timeout: float = 5.0) -> None:
        """Arm (or disarm): acknowledged and shown in the vehicle's HEARTBEAT."""
        self.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if armed else 0.0, timeout=timeout)
        if not self.wait(lambda s: s.armed == armed, timeout):
            raise SitlError(f"{'arm' if armed else 'disarm'} acknowledged but the HEARTBEAT does not show it")

    def param(self, name: str, timeout: float = 3.0) -> float:
        """A parameter's value (PARAM_REQUEST_READ, its PARAM_VALUE)."""
        t_end = time.monotonic() + timeout
        with self.cond:
            self.s.params.pop(name, None)
        while time.monotonic() < t_end:
            self.send("param_request_read", *self.target, name.encode(), -1)
            if self.wait(lambda s: name in s.params, min(1.0, max(0.0, t_end - time.monotonic()))):
                with self.cond:
                    return self.s.params[name]
        raise SitlError(f"no PARAM_VALUE for {name} within {timeout} s (no such parameter?)")

    def set_param(self, name: str, value: float, timeout: float = 3.0) -> None:
        """PARAM_SET, done when the vehicle's PARAM_VALUE says the new value."""
        t_end = time.monotonic() + timeout
        with self.cond:
            self.s.params.pop(name, None)
        while time.monotonic() < t_end:
            self.send("param_set", *self.target, name.encode(), float(value), MAV.MAV_PARAM_TYPE_REAL32)
            if self.wait(lambda s: name in s.params and math.isclose(s.params[name], value, rel_tol=1e-5,
                                                                     abs_tol=1e-6),
                         min(1.0, max(0.0, t_end - time.monotonic()))):
                return
        raise SitlError(f"PARAM_SET {name}={value}: no PARAM_VALUE saying so within {timeout} s")

    def velocity(self, v: float, yaw_rate: float) -> None:
        """A GUIDED set-point as a companion computer sends it: SET_POSITION_TARGET_LOCAL_NED in BODY_NED, velocity +
        yaw rate (``v`` m/s forward, ``yaw_rate`` rad/s clockwise)."""
        self.send("set_position_target_local_ned", 0, *self.target, MAV.MAV_FRAME_BODY_NED, 0x05E7, 0.0, 0.0, 0.0,
                  float(v), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(yaw_rate))

    def sign_with(self, key: bytes) -> None:
        """Sign every message this link sends from now on with ``key`` (MAVLink 2 signing, pymavlink's)."""
        with self._send_lock:
            self.conn.setup_signing(key, sign_outgoing=True)

    def setup_signing(self, key: bytes, timeout: float = 5.0) -> None:
        """SETUP_SIGNING: install ``key`` (32 bytes) in the autopilot, as a ground station does over its first
        link; done when a HEARTBEAT comes signed with that key. The pilot keeps sending unsigned (ArduPilot accepts
        unsigned messages on this first port whatever the key, libraries/GCS_MAVLink/GCS_Signing.cpp): it has the
        driver host's system and component ids (255, 190), and two signed senders with the same ids share one
        signing stream on the vehicle, whose timestamps must only grow, so each would see the other's refused as
        replays (found here: the signed host's set-points were dropped while the pilot signed too)."""
        if len(key) != 32:
            raise ValueError("a MAVLink 2 signing key is 32 bytes")
        with self.cond:
            n = self.s.signed_heartbeats
        self.send("setup_signing", *self.target, list(key), signing_timestamp())
        with self._send_lock:  # checks the vehicle's signatures; messages still unsigned on their way are taken
            self.conn.setup_signing(key, sign_outgoing=False, allow_unsigned_callback=lambda *_: True)
        if not self.wait(lambda s: s.signed_heartbeats > n, timeout):
            raise SitlError(f"SETUP_SIGNING sent; no signed HEARTBEAT within {timeout} s")


class Sitl:
    """One ArduPilot Rover SITL process and its pilot: ``with Sitl() as sitl: sitl.pilot.set_mode("GUIDED")``.

    ``model``: rover-skid (skid-steer, like the paper's Jackal), rover (Ackermann), motorboat, balancebot.
    ``params``: parameters written to an extra ``.parm`` file after the model's (so they are SITL's defaults with
    ``-w``); ``parm_files``: further ``.parm`` files. ``boot_speedup``: SIM_SPEEDUP while booting (then 1)."""

    def __init__(self, binary: str | Path | None = None, *, model: str = "rover-skid",
                 params: dict[str, float] | None = None, parm_files: Iterable[str | Path] = (),
                 boot_speedup: float = 10.0, boot_timeout: float = 60.0, instance: int | None = None,
                 keep_dir: bool = False) -> None:
        found = Path(binary) if binary is not None else find_sitl()
        if found is None or not found.is_file():
            raise SitlError(f"ArduPilot SITL not found at {binary or where_sitl_is_looked_for()}: set {ENV}")
        if model not in MODELS:
            raise SitlError(f"unknown SITL model {model!r}: one of {', '.join(MODELS)}")
        # absolute too: started in its own directory, a relative binary (``--sitl ../sitl/ardurover``) and the
        # default_params beside it are not found there
        self.binary = found.resolve()
        self.model = model
        self.params = dict(params or {})
        # absolute: SITL runs in its own directory, and a defaults file it cannot read is a PANIC
        self.parm_files = [Path(p).resolve() for p in parm_files]
        for p in self.parm_files:
            if not p.is_file():
                raise SitlError(f"no parameter file {p}")
        self.boot_speedup = boot_speedup
        self.boot_timeout = boot_timeout
        self.instance = instance
        self.keep_dir = keep_dir
        self.dir: Path | None = None
        self.proc: subprocess.Popen | None = None
        self.pilot: Pilot | None = None
        self.boot_s = math.nan  # wall time from start to real time with a position
        self.wipe = True  # -w: the first start wipes the stored parameters; a reboot keeps the storage

    # ------------------------------------------------------------------------------------------ endpoints
    def url(self, serial: int) -> str:
        """``tcp:127.0.0.1:PORT`` of SERIALn (0: the ground station, 1: the driver host, 2: a third link)."""
        assert self.instance is not None
        return f"tcp:127.0.0.1:{TCP_BASE + 10 * self.instance + (0 if serial == 0 else serial + 1)}"

    @property
    def driver_url(self) -> str:
        return self.url(1)

    @property
    def spare_url(self) -> str:
        return self.url(2)

    def log_tail(self, n: int = 1500) -> str:
        """The last characters SITL wrote on its stdout / stderr."""
        if self.dir is None or not (self.dir / "sitl.log").exists():
            return ""
        return (self.dir / "sitl.log").read_text(errors="replace")[-n:]

    def defaults(self) -> list[Path]:
        """The ``--defaults`` files: the model's upstream ones, the extra ones, then ``params``."""
        up = self.binary.parent / "default_params"
        files = [up / "rover.parm"] + ([up / f"{self.model}.parm"] if self.model != "rover" else [])
        files += self.parm_files
        if self.params:
            assert self.dir is not None
            extra = self.dir / "extra.parm"
            extra.write_text("".join(f"{k} {v}\n" for k, v in self.params.items()))
            files.append(extra)
        return files

    # ------------------------------------------------------------------------------------------ life
    def start(self) -> Sitl:
        """Start SITL and the pilot; return once the vehicle runs in real time with an EKF position, else raise
        :class:`SitlError` naming what did not come (and stop everything)."""
        t0 = time.monotonic()
        deadline = t0 + self.boot_timeout
        self.dir = Path(tempfile.mkdtemp(prefix="scmbridge-sitl-"))
        try:
            tried: list[int] = []
            fixed = self.instance is not None
            while True:
                if not fixed:
                    self.instance = free_instance(tried)
                    tried.append(self.instance)
                if self._launch(deadline) or fixed or len(tried) >= 5:
                    break
            if self.pilot is None:
                raise SitlError(f"SITL instance {self.instance} did not accept a ground station on {self.url(0)}"
                                f": {self.log_tail(600)}")
            self._boot(deadline)
            self.boot_s = time.monotonic() - t0
            return self
        except BaseException:
            self.stop()
            raise

    def _launch(self, deadline: float) -> bool:
        """Start the process on ``self.instance`` and connect the pilot; False if the process died (a port taken
        meanwhile by someone else)."""
        defaults = ",".join(str(p) for p in self.defaults())
        argv = [str(self.binary), "--model", self.model, "--speedup", f"{self.boot_speedup:g}", "-I",
                str(self.instance), *(["-w"] if self.wipe else []), "--defaults", defaults]
        assert self.dir is not None
        with open(self.dir / "sitl.log", "ab") as log:
            self.proc = subprocess.Popen(argv, cwd=self.dir, stdout=log, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True)
        t_end = min(deadline, time.monotonic() + 15.0)
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                self.proc = None
                return False
            try:
                self.pilot = Pilot(self.url(0))
                return True
            except OSError:
                time.sleep(0.05)  # it has not bound its port yet: nothing to await but the connect itself
        return True

    def _boot(self, deadline: float) -> None:
        pilot = self.pilot
        assert pilot is not None

        def left() -> float:
            if self.proc is None or self.proc.poll() is not None:
                raise SitlError(f"SITL exited while booting: {self.log_tail(600)}")
            if "PANIC" in self.log_tail(4000):  # it panics and then spins (e.g. a defaults file it cannot parse)
                raise SitlError(f"SITL panicked while booting: {self.log_tail(600)}")
            return max(0.0, deadline - time.monotonic())

        def until(pred: Callable[[_State], bool]) -> bool:
            """``pilot.wait`` in half-second slices, so that a SITL that died or panicked is seen at once."""
            while (rest := left()) > 0:
                if pilot.wait(pred, min(0.5, rest)):
                    return True
            return False

        if not until(lambda s: s.heartbeats > 0):
            raise SitlError(f"SITL boot: no HEARTBEAT on {pilot.url} within {self.boot_timeout} s")
        for msg_id, hz in ((MAV.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20), (MAV.MAVLINK_MSG_ID_ATTITUDE, 20),
                           (MAV.MAVLINK_MSG_ID_VFR_HUD, 10), (MAV.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 2)):
            pilot.interval(msg_id, hz)  # in vehicle time: faster in wall time while booting
        if not until(lambda s: s.position is not None):
            raise SitlError(f"SITL boot: no LOCAL_POSITION_NED (no EKF origin) within {self.boot_timeout} s; "
                            f"vehicle said {pilot.texts()[-4:]}")
        if not until(lambda s: s.ekf_flags & EKF_POS_HORIZ_ABS and s.mode not in ("INITIALISING", "unknown")):
            raise SitlError(f"SITL boot: the EKF has no absolute position (GPS) within {self.boot_timeout} s; "
                            f"vehicle said {pilot.texts()[-4:]}")
        pilot.set_param("SIM_SPEEDUP", 1.0, timeout=min(5.0, left()))

    def reboot(self, kill: signal.Signals = signal.SIGKILL) -> None:
        """The autopilot loses power and boots again on the same storage (``eeprom.bin``: its parameters, the
        signing key and timestamp) and instance: the process killed with ``kill``, started again without ``-w``,
        and booted as :meth:`start` does (a new pilot on SERIAL0)."""
        if self.pilot is not None:
            self.pilot.close()
            self.pilot = None
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, kill)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=5.0)
            self.proc = None
        self.wipe = False
        t0 = time.monotonic()
        deadline = t0 + self.boot_timeout
        try:
            if not self._launch(deadline) or self.pilot is None:
                raise SitlError(f"SITL instance {self.instance} did not come back on {self.url(0)}: "
                                f"{self.log_tail(600)}")
            self._boot(deadline)
            self.boot_s = time.monotonic() - t0
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """Close the pilot, kill the process group (SIGTERM, then SIGKILL after 3 s), remove the directory."""
        if self.pilot is not None:
            self.pilot.close()
            self.pilot = None
        if self.proc is not None:
            for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 5.0)):
                if self.proc.poll() is not None:
                    break
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, sig)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(timeout=wait)
            self.proc = None
        if self.dir is not None and not self.keep_dir:
            shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> Sitl:
        return self.start() if self.proc is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()
