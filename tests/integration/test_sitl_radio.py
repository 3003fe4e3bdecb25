"""A lab's own rover on day one, against ArduPilot's real Rover firmware in SITL (sim_learner/sitl.py): the radio on a
serial port, signing set up from a passphrase as ground stations do it, and one radio shared with a real MAVProxy.

Each test boots its own SITL (own directory, free instance) and, where the driver host runs, its own Zenoh router on a
free port (tests/integration/test_sitl.py's :class:`Rig`); every process is bounded and cleaned up. Marked ``sitl``:
skipped without the binary, failed under ``make test-sitl``; MAVProxy comes from the dev lock.
"""

from __future__ import annotations

import importlib.util
import math
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest

from bridge.core.auth import load_key
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.procs import Children, free_udp_port, stop_group
from drivers.mavlink.signing import passphrase_key
from sim_learner.sitl import MAV, Pilot, Sitl, SitlError
from tests.integration.test_sitl import Rig, _engage_by_the_pilot, _reach, _sitl_binary
from tests.ptyrelay import PtyRelay

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(150)]

PASSPHRASE = "correct-horse-battery-staple"  # one word: MAVProxy's `signing setup` takes its first argument only


@pytest.fixture
def sitl() -> Iterator[Sitl]:
    with Sitl(_sitl_binary(), model="rover-skid") as s:
        yield s


@pytest.fixture
def router() -> Iterator[tuple[int, object, Children]]:
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        yield port, session, kids


def _rig(tmp_path: Path, router, vehicle: object, link: str = "") -> Rig:
    """The driver host's rig on ``vehicle.driver_url``, with more ``[link.mavlink]`` lines ``link``."""
    port, session, kids = router
    rig = Rig(tmp_path, vehicle, session, kids)
    rig.port = port
    rig.cfg.write_text(rig.cfg.read_text() + link)
    return rig


def test_the_driver_host_drives_the_rover_through_a_serial_port_as_a_radio_is_opened(tmp_path, sitl, router) -> None:
    """``url = "/dev/pts/N"`` with ``baud``: pymavlink opens it with pyserial (the robot lock's), as a telemetry radio's
    ``/dev/ttyUSB0``; the far end of the terminal is SITL's SERIAL1. The host opens the link, the pilot engages, the
    rover reaches the commanded speed and the person's HOLD is honoured."""
    import serial  # the robot lock's pyserial: pymavlink's serial ports need it

    assert serial.__version__
    with PtyRelay(int(sitl.driver_url.rsplit(":", 1)[1])) as pty:
        rig = _rig(tmp_path, router, SimpleNamespace(driver_url=pty.path, pilot=sitl.pilot), "baud = 57600\n")
        try:
            assert f'url = "{pty.path}"' in rig.cfg.read_text() and pty.path.startswith("/dev/pts/")
            rig.host()
            rig.stream(0.6, 0.0)
            _engage_by_the_pilot(rig)
            assert _reach(sitl.pilot, 0.6, 10), sitl.pilot.speed
            assert pty.relayed[0] > 0 and pty.relayed[1] > 0
            sitl.pilot.set_mode("HOLD")
            st = rig.wait_state("waiting", 5, after=len(rig.status))
            assert "operator took control: mode HOLD" in st.text, st.text
        finally:
            rig.close()


def _scm(args: list[str], timeout: float = 60, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args], capture_output=True, text=True, timeout=timeout,
                          input=stdin)


def test_keys_mavlink_install_sends_the_passphrases_key_and_confirms_signed_taken_unsigned_refused(
        tmp_path, sitl) -> None:
    """``scmbridge keys mavlink --passphrase P --install --driver FILE`` on SITL's SERIAL1 (ArduPilot refuses unsigned
    messages there once it has a key; SERIAL0, its USB port, never does): the key file holds SHA-256(P), the vehicle
    took it (checked again on a third link: unsigned unanswered, signed answered), and nothing else changed (mode,
    arming)."""
    cfg = tmp_path / "driver.toml"
    cfg.write_text(f'[link.mavlink]\nurl = "{sitl.driver_url}"\nopen_timeout = 20\n')
    key_file = tmp_path / "rover.key"
    mode_before = sitl.pilot.mode
    r = _scm(["keys", "mavlink", "--robot", "rover1", "--out", str(key_file), "--passphrase", "-", "--install",
              "--driver", str(cfg)], stdin=PASSPHRASE + "\n")
    assert r.returncode == 0, r.stdout + r.stderr
    assert load_key(key_file, "mavlink") == passphrase_key(PASSPHRASE)
    assert "ok   a request signed with the key: MAV_RESULT_ACCEPTED" in r.stdout, r.stdout
    assert "ok   an unsigned request: refused (no answer)" in r.stdout, r.stdout
    third = Pilot(sitl.spare_url, source_system=254)
    try:
        assert third.wait(lambda s: s.heartbeats > 0, 5)
        with pytest.raises(SitlError, match="no COMMAND_ACK"):  # unsigned: refused
            third.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_AUTOPILOT_VERSION, timeout=2.0)
        third.sign_with(passphrase_key(PASSPHRASE))  # signed with the passphrase's key: answered
        third.command(MAV.MAV_CMD_REQUEST_MESSAGE, MAV.MAVLINK_MSG_ID_AUTOPILOT_VERSION, timeout=3.0)
    finally:
        third.close()
    assert sitl.pilot.mode == mode_before and not sitl.pilot.armed
    # the same passphrase again: the same key, kept without --force; another one is refused without it
    again = _scm(["keys", "mavlink", "--robot", "rover1", "--out", str(key_file), "--passphrase", PASSPHRASE])
    assert again.returncode == 0, again.stderr
    other = _scm(["keys", "mavlink", "--robot", "rover1", "--out", str(key_file), "--passphrase", "another"])
    assert other.returncode != 0 and "--force" in other.stderr, other.stderr


def test_keys_mavlink_install_says_so_when_the_port_still_takes_unsigned_messages(tmp_path, sitl) -> None:
    """On SERIAL0 (ArduPilot's USB port, which takes unsigned messages whatever the key) the key is installed and
    signed requests answered, but the unsigned one is answered too: exit 1, and the line says why."""
    cfg = tmp_path / "driver.toml"
    sitl.pilot.close()  # the person's ground station hangs up: SERIAL0 takes one connection, the "USB cable"
    cfg.write_text(f'[link.mavlink]\nurl = "{sitl.url(0)}"\nopen_timeout = 20\n')
    r = _scm(["keys", "mavlink", "--robot", "rover1", "--out", str(tmp_path / "k"), "--passphrase", PASSPHRASE,
              "--install", "--driver", str(cfg)])
    assert r.returncode == 1, r.stdout + r.stderr
    assert "FAIL an unsigned request was answered" in r.stdout and "USB port" in r.stdout, r.stdout


class MavProxy:
    """A real MAVProxy (the dev lock's), headless: ``--master`` the vehicle's port, ``--out udp:127.0.0.1:PORT`` for
    the driver host, commands typed on its standard input as a person types them; its output read by a thread."""

    def __init__(self, master: str, out_port: int, workdir: Path, argv: list[str] | None = None) -> None:
        argv = argv or [sys.executable, "-m", "MAVProxy.mavproxy", "--master", master, "--out",
                        f"udp:127.0.0.1:{out_port}", "--no-state", "--state-basedir", str(workdir),
                        "--streamrate", "10"]
        self.proc = subprocess.Popen(argv, cwd=workdir, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, start_new_session=True, bufsize=1)
        self.lines: queue.Queue[str] = queue.Queue()
        self.said: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.said.append(line.rstrip())
            self.lines.put(line)

    def type(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(self, text: str, timeout: float) -> bool:
        """A line containing ``text`` within ``timeout`` s (said since the last expect or before)."""
        if any(text in s for s in self.said):
            return True
        t_end = time.monotonic() + timeout
        while (left := t_end - time.monotonic()) > 0:
            try:
                if text in self.lines.get(timeout=left):
                    return True
            except queue.Empty:
                return False
        return False

    def close(self) -> None:
        stop_group(self.proc, 3.0)


@pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None and not os.environ.get("SCMBRIDGE_SITL_REQUIRED"),
                    reason="MAVProxy is not installed (it is in requirements/dev.txt)")
def test_one_radio_shared_with_mavproxy_signing_set_by_it_and_its_mode_switch_honoured(tmp_path, sitl,
                                                                                        router) -> None:
    """The driver host beside a ground station on one radio: MAVProxy holds the vehicle's port (SERIAL1, which refuses
    unsigned messages once signed), the host listens on MAVProxy's ``--out`` with a companion computer's ids (the
    vehicle's system id, component 191), so neither collides with MAVProxy's 255. The person types in MAVProxy:
    ``signing setup PASSPHRASE`` (the host's key is ``keys mavlink --passphrase`` of the same), ``mode GUIDED``,
    ``arm throttle``: the host drives at the commanded speed, signed; then ``mode HOLD``: the host says the operator
    took control and stops commanding, and the vehicle stays in HOLD."""
    key_file = tmp_path / "rover.key"
    r = _scm(["keys", "mavlink", "--robot", "rover1", "--out", str(key_file), "--passphrase", PASSPHRASE])
    assert r.returncode == 0, r.stderr
    out_port = free_udp_port()
    gcs = MavProxy(sitl.driver_url, out_port, tmp_path)
    try:
        assert gcs.expect("Detected vehicle 1:1", 30) or gcs.expect("online system 1", 1), gcs.said[-20:]
        gcs.type(f"signing setup {PASSPHRASE}")
        assert gcs.expect("Sent secret_key", 10), gcs.said[-20:]
        rig = _rig(tmp_path, router, SimpleNamespace(driver_url=f"udpin:127.0.0.1:{out_port}", pilot=sitl.pilot),
                   f'source_system = 1\nsource_component = 191\nsigning_key_file = "{key_file}"\n')
        try:
            rig.host()
            rig.stream(0.5, 0.0)
            st = rig.wait_state("waiting", 60)
            assert "waiting for the operator" in st.text, st.text
            gcs.type("mode GUIDED")
            assert sitl.pilot.wait(lambda s: s.mode == "GUIDED", 10), gcs.said[-20:]
            gcs.type("arm throttle")
            assert sitl.pilot.wait(lambda s: s.armed, 15), gcs.said[-20:]
            early = rig.wait_state("driving", 10)
            assert early.ok
            assert _reach(sitl.pilot, 0.5, 10), sitl.pilot.speed
            late = rig.wait_state("driving", 5, after=len(rig.status))
            # The vehicle's messages come signed with the key: while it drives none is refused, and many arrive. The
            # few it sent unsigned before it took MAVProxy's SETUP_SIGNING may still have been on their way to the host
            # when it opened its port (they are refused, as they must be), hence the bound on the early count.
            assert early.counters["link_bad_signatures"] <= 5, early.counters
            assert late.counters["link_bad_signatures"] == early.counters["link_bad_signatures"], late.counters
            assert late.counters["frames_received"] - early.counters["frames_received"] >= 10, late.counters
            gcs.type("mode HOLD")
            st = rig.wait_state("waiting", 5, after=len(rig.status))
            assert "operator took control: mode HOLD" in st.text, st.text
            assert sitl.pilot.wait(lambda s: s.position is not None and math.hypot(s.position.vx, s.position.vy)
                                   < 0.05, 10)
            assert not sitl.pilot.wait(lambda s: s.mode != "HOLD", 3.0)  # never taken back by the host
            assert rig.applied[-1].v == 0.0 and rig.applied[-1].reason == "disengaged"
        finally:
            rig.close()
    finally:
        gcs.close()


def _lines(out: str) -> dict[str, list[str]]:
    """``scmbridge doctor``'s lines by check name."""
    found: dict[str, list[str]] = {}
    for ln in out.splitlines():
        parts = ln.split(None, 2)
        if len(parts) == 3 and parts[0] in ("ok", "warn", "FAIL"):
            found.setdefault(parts[1], []).append(f"{parts[0]} {parts[2]}")
    return found


@pytest.fixture
def slow_sitl() -> Iterator[Sitl]:
    """A rover whose GUIDED speed cap is 0.6 m/s and turn-rate cap 30 deg/s (a lab's small rover)."""
    with Sitl(_sitl_binary(), model="rover-skid", params={"WP_SPEED": 0.6, "ATC_STR_RAT_MAX": 30}) as s:
        yield s


@pytest.mark.timeout(240)
def test_doctor_link_mavlink_names_what_the_rover_lacks_with_the_fix_and_changes_nothing(tmp_path, slow_sitl) -> None:
    """``scmbridge doctor --driver FILE --link mavlink`` on SITL as it boots (GCS failsafe off, no HOLD position on the
    RC mode switch, no signing, hard limits wider than WP_SPEED / ATC_STR_RAT_MAX): each named with its fix, nothing
    on the vehicle changed; then the person applies the fixes (parameters from the ground station, the key installed,
    the driver's limits narrowed) and the same checks pass."""
    sitl = slow_sitl
    cfg = tmp_path / "driver.toml"
    cfg.write_text('robot = "rover1"\n[driver.hard_limits]\nv = [-1.0, 1.0]\nw = [-1.0, 1.0]\n\n'
                   f'[link.mavlink]\nurl = "{sitl.driver_url}"\n')
    doctor = ["doctor", "--driver", str(cfg), "--link", "mavlink", "--duration", "0.3"]
    r = _scm(doctor, timeout=90)
    found = _lines(r.stdout)
    assert found["guided"] == ["ok ArduPilot Rover, mode MANUAL: GUIDED is its mode for a companion's set-points "
                               "(engage: the GCS or scmbridge engage)"], r.stdout
    assert "FS_GCS_ENABLE 1, FS_ACTION 2 (Hold)" in found["gcs-fs"][0] and found["gcs-fs"][0].startswith("warn")
    assert found["rc-hold"][0].startswith("warn") and "MODE1..MODE6 = 4" in found["rc-hold"][0]
    assert found["signing"][0].startswith("warn") and "--passphrase WORD --install" in found["signing"][0]
    assert found["arming"] == ["ok every arming check on (ARMING_CHECK 1)"], r.stdout
    assert "v = [0.05, 0.6], w = [-0.5236, 0.5236]" in found["range"][0], r.stdout
    assert found["range"][1].startswith("warn [driver.hard_limits]") and "v = [-0.6, 0.6]" in found["range"][1]
    assert sitl.pilot.param("FS_GCS_ENABLE") == 0 and sitl.pilot.mode == "MANUAL" and not sitl.pilot.armed
    # the person's fixes
    sitl.pilot.set_param("FS_GCS_ENABLE", 1)
    sitl.pilot.set_param("MODE6", 4)
    key = tmp_path / "rover.key"
    r = _scm(["keys", "mavlink", "--robot", "rover1", "--out", str(key), "--passphrase", PASSPHRASE, "--install",
              "--driver", str(cfg)])
    assert r.returncode == 0, r.stdout + r.stderr
    cfg.write_text('robot = "rover1"\n[driver.hard_limits]\nv = [-0.6, 0.6]\nw = [-0.5, 0.5]\n\n'
                   f'[link.mavlink]\nurl = "{sitl.driver_url}"\nsigning_key_file = "{key}"\n')
    r = _scm(doctor, timeout=90)
    found = _lines(r.stdout)
    for name in ("guided", "rc-hold", "gcs-fs", "guided-to", "signing", "arming", "range"):
        assert all(x.startswith("ok") for x in found[name]), (name, r.stdout)
    assert found["signing"] == [f"ok on: the vehicle's messages verify with {key}"]
    assert len(found["range"]) == 1


def test_mission_place_puts_the_mission_where_the_rover_stands_in_the_ekf_origins_frame(tmp_path, sitl,
                                                                                       router) -> None:
    """``scmbridge mission place FILE --robot R`` with the driver host on SITL: the rover driven away from where it
    booted and turned, then held by the person (HOLD) and standing still; the placed mission's start is the pose the
    vehicle itself reports (LOCAL_POSITION_NED east/north of the EKF origin, ATTITUDE's yaw as an ENU heading) within
    5 cm and 3 degrees, its frame ``ekf-origin``; a moving rover is refused."""
    rig = _rig(tmp_path, router, sitl)
    try:
        rig.host()
        rig.stream(0.6, 0.4)
        _engage_by_the_pilot(rig)
        assert _reach(sitl.pilot, 0.6, 10), sitl.pilot.speed
        place = ["mission", "place", "paper-s-path", "--robot", rig.robot, "--connect", tcp(rig.port), "--out",
                 str(tmp_path / "placed.toml")]
        moving = _scm(place)
        assert moving.returncode == 2 and "the robot is moving" in moving.stderr, moving.stdout + moving.stderr
        sitl.pilot.set_mode("HOLD")
        # at rest SITL's reported speed wanders up to about 0.02 m/s (test_sitl.py)
        assert sitl.pilot.wait(lambda s: s.position is not None and math.hypot(s.position.vx, s.position.vy) < 0.04
                               and s.attitude is not None and abs(s.attitude.yawspeed) < 0.02, 15), sitl.pilot.speed
        r = _scm(place)
        assert r.returncode == 0, r.stdout + r.stderr
        north, east = sitl.pilot.position
        with sitl.pilot.cond:
            yaw = float(sitl.pilot.s.attitude.yaw)
        assert math.hypot(north, east) > 1.0  # it did drive away from the origin
        from bridge.core.config import load_mission_spec

        placed = load_mission_spec(str(tmp_path / "placed.toml"))
        assert placed.frame == "ekf-origin"
        x, y, th = placed.start
        assert math.hypot(x - east, y - north) < 0.05, (placed.start, east, north)
        assert abs(math.remainder(th - (math.pi / 2 - yaw), 2 * math.pi)) < math.radians(3), (th, yaw)
    finally:
        rig.close()
