"""``scmbridge doctor``: a preflight before a lab drives: what is wrong, and what to do about it.

Each check prints one line, ``ok``, ``warn`` or ``FAIL``, its name and what it found or what to fix:

- ``config``: the station and/or driver files (``--station``, ``--driver``) parse and are sane;
- ``router``: the Zenoh router the configuration (``--zenoh-config`` or ``--connect``) names is reachable, and
  (``reach``) what this identity sees through it: the nodes' statuses and the driver hosts answering its estop
  query, as ``status --all`` and ``estop --all`` will;
- ``tls``: for a TLS configuration, each certificate and key it names exists, the certificates are signed by the
  CA it names (one CA), and none expires within ``--expiry-days`` (a warning) or has expired (a failure);
- ``access``: a router configuration with access control on is named as such (rules and subjects counted); one
  without says that anyone on its network may publish commands;
- ``robot``: each robot's driver host asked over Zenoh (:mod:`bridge.tools.doctor_fleet`): its estop latch as it holds
  it, its state, and where it runs (this machine or its host's name);
- ``state``: the state directory (``SCMBRIDGE_STATE_DIR``, ...: which one is named) exists or can be created, takes a
  file (written, fsynced and removed) and is 0700; ``latch``: only for a driver host on this machine (the
  ``--driver`` file's robot, or one that answered from here), what a driver host starting now would take: released
  (signed by that host), latched (by whom), latched because the file is missing, unreadable or not the host's own,
  copied back (older than its record), beside a marker of another key, or deleted with its marker (its record outside
  the state directory remembers), or "first start in this state directory: no estop history" (a host that ran with
  another state directory left its latch there); ``station``: each mission and pair store file there is the
  station's own (its tag verifies), or why not;
- ``can``: for a SocketCAN link, the interface exists and is up (with the command that brings it up);
- ``auth``: (``--link``) whether the link authenticates what it obeys: a warning for the UDP link with
  ``insecure = true`` and for MAVLink without signing (anyone on the network can drive the robot);
- ``guided``, ``rc-hold``, ``gcs-fs``, ``rc-fs``, ``guided-to``, ``signing``, ``arming``, ``prearm``, ``range``:
  (``--link mavlink``) what the project relies on in an ArduPilot Rover, read over the link and never changed, each
  with its fix (bridge/tools/doctor_mavlink.py);
- ``vehicle``: the link opens and the vehicle answers (``--link`` with ``--driver``; it is never engaged: no
  mode change, arming or closed loop), and its own failsafe: how long it would drive on if the driver host died,
  a warning beyond the driver's ``max_drive_on_s``.

Run it before starting the driver host (a serial port or a UDP port can be opened by one process only). Exit
status: 0 when nothing failed (warnings allowed), 1 otherwise.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import stat
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from bridge.core import wire as M
from bridge.core.args import positive_float
from bridge.core.config import load_station
from bridge.core.errors import UsageError
from bridge.core.paths import state_dir
from bridge.nodes.driver_config import load_driver
from bridge.nodes.latch_record import record_dir, record_file
from bridge.nodes.latch_store import inspect_latch, latch_marker
from bridge.nodes.node import add_zenoh_args, endpoints_tried, zenoh_config
from bridge.nodes.station_tags import file_problem
from bridge.nodes.tlsid import cert_names
from bridge.nodes.zsession import open_session
from bridge.tools.doctor_fleet import fleet_report
from drivers import link_names
from drivers.base import link_unauthenticated


@dataclass(frozen=True)
class Check:
    """One finding: ``level`` ok / warn / FAIL, the check's ``name``, and in words what was found or what to do."""

    level: str
    name: str
    text: str

    def line(self) -> str:
        return f"{self.level:<5} {self.name:<8} {self.text}"


def _json(conf: zenoh.Config, key: str) -> object:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # a key the config does not have
        return None


def check_router(args: argparse.Namespace, conf: zenoh.Config, listen_s: float) -> list[Check]:
    """The router answers, and what this identity may see through it: the statuses it hears and the driver hosts
    that answer its estop query (the tools it will use: status --all, estop --all) within ``listen_s``."""
    try:
        with open_session(conf) as session:
            heard: set[str] = set()
            sub = session.declare_subscriber(f"{M.PREFIX}/*/status/**",
                                             lambda s: heard.add("/".join(str(s.key_expr).split("/")[1::2])))
            answered = {str(r.ok.key_expr).split("/")[1] for r in session.get(f"{M.PREFIX}/*/estop",
                                                                              timeout=min(1.0, listen_s))
                        if r.ok is not None}
            time.sleep(max(0.0, listen_s - 1.0))
            sub.undeclare()
    except UsageError as exc:
        if "refuses this certificate" in str(exc):  # the router is up: it is the certificate
            return [Check("FAIL", "router", str(exc))]
        return [Check("FAIL", "router", f"{exc} (start the router: scmbridge-router.service, or scmbridge router "
                                        "--zenoh-config router.json5)")]
    out = [Check("ok", "router", f"reached ({endpoints_tried(args)})")]
    if heard or answered:
        out.append(Check("ok", "reach", f"this identity hears {len(heard)} node statuses ({', '.join(sorted(heard))})"
                                         f"; {len(answered)} driver hosts answer its estop query"))
    else:
        out.append(Check("warn", "reach", f"no status heard in {listen_s:g} s and no driver host answered an estop "
                                           "query: nothing is running yet, or the router's access control does not "
                                           "let this identity see it (use the operator or observer certificate)"))
    return out


def _openssl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["openssl", *args], capture_output=True, text=True, timeout=30)


def check_tls(conf: zenoh.Config, expiry_days: float) -> list[Check]:
    tls = _json(conf, "transport/link/tls")
    if not isinstance(tls, dict) or not any(isinstance(v, str) and v for v in tls.values()):
        return [Check("warn", "tls", "no TLS in this Zenoh configuration: traffic is neither encrypted nor "
                                     "authenticated: anyone who can reach this Zenoh session — on the loopback "
                                     "default, any user of this machine — may engage, start missions and release "
                                     "estops (scmbridge deploy makes the lab's TLS configuration)")]
    if shutil.which("openssl") is None:
        return [Check("warn", "tls", "openssl is not installed: certificates not checked")]
    ca = tls.get("root_ca_certificate")
    out: list[Check] = []
    files = {k: v for k, v in tls.items() if isinstance(v, str) and k.endswith(("_certificate", "_private_key"))}
    for key, path in sorted(files.items()):
        if not Path(path).is_file():
            out.append(Check("FAIL", "tls", f"{key} {path}: no such file"))
            continue
        if not key.endswith("_certificate"):
            continue
        end = _openssl("x509", "-in", path, "-noout", "-enddate", "-subject")
        if end.returncode != 0:
            out.append(Check("FAIL", "tls", f"{path}: not a certificate ({end.stderr.strip()[:120]})"))
            continue
        fields = dict(line.split("=", 1) for line in end.stdout.strip().splitlines() if "=" in line)
        expires = dt.datetime.strptime(fields["notAfter"].strip(), "%b %d %H:%M:%S %Y %Z").replace(tzinfo=dt.UTC)
        left = (expires - dt.datetime.now(dt.UTC)).total_seconds() / 86400
        subject = fields.get("subject", "").strip()
        if left <= 0:
            out.append(Check("FAIL", "tls", f"{path} ({subject}) expired on {expires:%Y-%m-%d}: issue a new one"))
        elif left < expiry_days:
            out.append(Check("warn", "tls", f"{path} ({subject}) expires in {left:.0f} days ({expires:%Y-%m-%d})"))
        else:
            out.append(Check("ok", "tls", f"{path} ({subject}) valid until {expires:%Y-%m-%d}"))
        if ca and key != "root_ca_certificate" and Path(ca).is_file():
            ver = _openssl("verify", "-CAfile", ca, path)
            if ver.returncode != 0:
                mine, lab = cert_names(path), cert_names(ca)
                names = (f" (issued by CA {mine[1]!r}, the lab's is {lab[0]!r})" if mine and lab else "")
                out.append(Check("FAIL", "tls", f"{path} is not signed by the CA {ca}{names}: every peer will refuse "
                                                "it (all certificates of a lab come from one CA)"))
    return out


def check_access(conf: zenoh.Config) -> Check:
    ac = _json(conf, "access_control")
    mode = _json(conf, "mode")
    if isinstance(ac, dict) and ac.get("enabled"):
        return Check("ok", "access", f"access control on, default {ac.get('default_permission', 'deny')}: "
                                     f"{len(ac.get('rules', []))} rules, {len(ac.get('subjects', []))} subjects")
    if mode == "router":
        return Check("warn", "access", "this router has no access control: anyone who reaches it may publish "
                                       "commands (scmbridge deploy acl makes the lab's rules)")
    return Check("ok", "access", "a client: the router's rules apply (check the router's configuration)")


def check_can(channel: str, interface: str) -> Check:
    if interface != "socketcan":
        return Check("ok", "can", f"interface {interface} (no SocketCAN device to check)")
    state = Path(f"/sys/class/net/{channel}/operstate")
    fix = f"sudo ip link set {channel} up type can bitrate 500000 restart-ms 100"
    if not state.exists():
        return Check("FAIL", "can", f"no CAN interface {channel} (adapter unplugged? driver not loaded?); then: {fix}")
    text = state.read_text().strip()
    if text not in ("up", "unknown"):
        return Check("FAIL", "can", f"{channel} is {text}: {fix}")
    return Check("ok", "can", f"{channel} is up")


def _probe(directory: Path) -> None:
    """Write, fsync and remove a small file in ``directory`` (what a latch save needs; raises OSError if it cannot)."""
    probe = directory / f".doctor-{os.getpid()}.probe"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"doctor\n" * 64)
            os.fsync(fd)
        finally:
            os.close(fd)
    finally:
        probe.unlink(missing_ok=True)


def check_state(robot: str | None) -> list[Check]:
    """The state directory the driver host and the station would use (``bridge.core.paths.state_dir``): it exists
    or can be created, takes a file and is the user's alone; then each robot's estop latch as a driver host starting
    now would take it (``robot``: the driver's; None: every robot with a latch or a marker there)."""
    d = state_dir()
    if not d.exists():
        parent = d
        while not parent.exists() and parent.parent != parent:
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            return [Check("FAIL", "state", f"state directory {d} does not exist and cannot be created ({parent} is "
                                           "not a writable directory): set SCMBRIDGE_STATE_DIR, or StateDirectory= "
                                           "in the unit")]
        return [Check("warn", "state", f"state directory {d} does not exist yet (the first start creates it, "
                                       "0700): first start in this state directory: no estop history")]
    if not d.is_dir():
        return [Check("FAIL", "state", f"state directory {d} is not a directory")]
    try:
        _probe(d)
    except OSError as exc:
        return [Check("FAIL", "state", f"state directory {d} does not take a file ({exc.strerror or exc}): an estop "
                                       "could not be saved (the driver host refuses to engage then); free space or "
                                       "fix its permissions")]
    mode = stat.S_IMODE(d.stat().st_mode)
    out = [Check("warn", "state", f"state directory {d} is mode {mode:o}: others may read the latch key or replace "
                                  f"the estop latch; chmod 700 {d}") if mode & 0o077
           else Check("ok", "state", f"state directory {d} (0700, writable)")]
    here = record_file(d / "estop-x.bin").name.rsplit("-", 1)[1]  # this state directory's records' suffix
    robots = [robot] if robot else sorted(
        {p.name[len("estop-"):].rsplit(".", 1)[0] for p in d.glob("estop-*") if p.suffix in (".bin", ".installed")}
        | {p.name[len("estop-"):-len(here) - 1] for p in record_dir().glob(f"estop-*-{here}")})
    for r in robots:
        path = d / f"estop-{r}.bin"
        marker = latch_marker(path)
        if not os.path.lexists(path) and not os.path.lexists(marker) and not os.path.lexists(record_file(path)):
            out.append(Check("warn", "latch", f"{r}: first start in this state directory: no estop history (a driver "
                                              f"host for {r} that ran with another state directory left its latch "
                                              "there: SCMBRIDGE_STATE_DIR must stay the same)"))
            continue
        latch, problem = inspect_latch(path)
        if problem:
            out.append(Check("warn", "latch", f"{r}: a driver host starting now is latched: {problem} (look at the "
                                              f"robot, then scmbridge estop --robot {r} --release)"))
        elif latch.latched:
            out.append(Check("warn", "latch", f"{r}: estop latched by {latch.source or 'unknown'}"
                                              + (f" ({latch.reason})" if latch.reason else "")))
        else:
            out.append(Check("ok", "latch", f"{r}: released (saved by its driver host; estop history since "
                                            f"{dt.datetime.fromtimestamp(marker.stat().st_mtime):%Y-%m-%d %H:%M})"))
    for kind, pattern in (("control", "mission-*.bin"), ("store", "pairs-*.bin")):
        for f in sorted(d.glob(pattern)):  # the station's files: its own (its tag), or changed while it was down
            problem = file_problem(kind, f)
            out.append(Check("warn", "station", f"{f.name}: {problem}") if problem
                       else Check("ok", "station", f"{f.name}: the station's own (its tag verifies)"))
    return out


def local_state(driver_robot: str | None, here: list[str]) -> list[Check]:
    """This machine's state directory (:func:`check_state`), and the latches in it only of the robots whose driver
    host runs here (``driver_robot``: the ``--driver`` file's; ``here``: those that answered from this machine): an
    operator's console holds no robot's latch, and a file left there is no robot's."""
    robots = sorted({*here, *([driver_robot] if driver_robot else [])})
    if not robots:
        found = [c for c in check_state(None) if c.name != "latch"]
        return [*found, Check("ok", "latch", "no driver host on this machine (none answered from here, no --driver): "
                                             "its state directory holds no robot's latch; each robot's own is "
                                             "asked over Zenoh (the robot lines)")]
    out: list[Check] = []
    for k, r in enumerate(robots):
        out += [Check(c.level, c.name, f"{c.text} (this machine's driver host)" if c.name == "latch" else c.text)
                for c in check_state(r) if k == 0 or c.name == "latch"]
    return out


def check_auth(link: str, link_cfg: object) -> list[Check]:
    """Whether the link authenticates what it obeys (drivers.base.link_unauthenticated)."""
    why = link_unauthenticated(link_cfg)
    if why:
        fix = {"udp": "make a key (scmbridge keys udp --robot R) and name it in [link.udp] key_file",
               "mavlink": "make a key (scmbridge keys mavlink --robot R), name it in [link.mavlink] signing_key_file "
                          "and give it to the autopilot"}.get(link, "")
        return [Check("warn", "auth", f"link {link}: {why}: link unauthenticated: anyone on the network can drive "
                                      "it" + (f"; {fix}" if fix else ""))]
    if hasattr(link_cfg, "unauthenticated"):
        return [Check("ok", "auth", f"link {link}: authenticated")]
    return []


#: link reasons that mean the vehicle has not been heard from (drivers.base.LinkReason)
SILENT = ("link_down", "no_heartbeat", "no_telemetry")
#: how long the vehicle has to answer once its link is open, s (a CAN controller's Heartbeat is every 100 ms, a UDP
#: robot's state every 50 ms, a MAVLink HEARTBEAT every second: the MAVLink link's open already waits for one)
ANSWER_S = 2.0


def _answer(driver) -> object:
    """The link's health once the vehicle has answered, or after :data:`ANSWER_S` (the link polled meanwhile)."""
    end = time.monotonic() + ANSWER_S
    while True:
        now = time.monotonic()
        driver.poll(now)
        h = driver.health(now)
        if (h.connected and h.reason not in SILENT) or now >= end:
            return h
        time.sleep(0.02)


def check_vehicle(link: str, link_cfg: object, max_drive_on: float) -> list[Check]:
    from drivers import open_driver
    from drivers.base import DriverError

    driver = open_driver(link, link_cfg)
    try:
        driver.open(time.monotonic())
    except DriverError as exc:
        return [Check("FAIL", "vehicle", f"link {link}: {exc}")]
    try:
        h = _answer(driver)
        if not h.connected or h.reason in SILENT:
            return [Check("FAIL", "vehicle", f"link {link}: the vehicle does not answer within {ANSWER_S:g} s: "
                                             f"{h.text}")]
        fs = driver.failsafe()
        out = [Check("ok", "vehicle", f"link {link}: the vehicle answers ({h.text})")]
        if fs.drive_on_s is None or fs.drive_on_s > max_drive_on:
            out.append(Check("warn", "failsafe", f"{fs.text}: more than max_drive_on_s = {max_drive_on:g} s; "
                                                 "see deploy/ROBOT.md, what the vehicle does when the host dies"))
        else:
            out.append(Check("ok", "failsafe", fs.text))
        return out
    finally:
        driver.close(disarm=False, stop_timeout=0.0)


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--station", default=None, help="the station's configuration file to check")
    ap.add_argument("--driver", default=None, help="the driver host's configuration file to check")
    ap.add_argument("--link", choices=link_names(), default=None,
                    help="with --driver: open this link and check the vehicle and its failsafe (never engaged)")
    ap.add_argument("--expiry-days", type=positive_float, default=14.0,
                    help="warn when a certificate expires within this many days")
    ap.add_argument("--duration", type=positive_float, default=2.5,
                    help="seconds to listen for the nodes' statuses through the router")
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    checks: list[Check] = []

    def step(fn: Callable[[], list[Check] | Check]) -> None:
        found = fn()
        for c in found if isinstance(found, list) else [found]:
            checks.append(c)
            print(c.line(), flush=True)

    driver_cfg = None
    for kind, path, load in (("station", args.station, load_station), ("driver", args.driver, load_driver)):
        if path is None:
            continue
        try:
            cfg = load(path)
        except UsageError as exc:
            step(lambda exc=exc: Check("FAIL", "config", str(exc)))
            continue
        step(lambda kind=kind, path=path: Check("ok", "config", f"{kind} {path}"))
        if kind == "driver":
            driver_cfg = cfg
    conf = zenoh_config(args)
    step(lambda: check_router(args, conf, args.duration))
    robots, here = fleet_report(conf, args.duration)  # the robots asked over Zenoh (bridge/tools/doctor_fleet.py)
    step(lambda: [Check(level, "robot", text) for level, text in robots])
    step(lambda: local_state(driver_cfg.robot if driver_cfg is not None else None, here or []))
    step(lambda: check_tls(conf, args.expiry_days))
    step(lambda: check_access(conf))
    if args.link is not None:
        if driver_cfg is None:
            raise UsageError("--link needs --driver FILE (the link's settings)")
        link_cfg = getattr(driver_cfg.link, args.link)
        if args.link == "can":
            step(lambda: check_can(link_cfg.channel, link_cfg.interface))
        step(lambda: check_auth(args.link, link_cfg))
        if args.link == "mavlink":  # what the project relies on in an ArduPilot Rover (bridge/tools/doctor_mavlink.py)
            step(lambda: __import__("bridge.tools.doctor_mavlink", fromlist=["_"]).check_mavlink(driver_cfg))
        step(lambda: check_vehicle(args.link, link_cfg, driver_cfg.driver.max_drive_on_s))
    failed = [c for c in checks if c.level == "FAIL"]
    print(f"{len(checks)} checks: {len(failed)} failed, {sum(c.level == 'warn' for c in checks)} warnings")
    return 1 if failed else 0
