"""``scmbridge doctor``: one line per check saying what is wrong and what to do, against a real router, a real
emulated rover (never engaged) and real certificates made with openssl."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest

from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from sim_learner.dynamics import mpc_learner
from sim_learner.mavlink_rover import MavlinkRover
from sim_learner.vehicle import SimVehicle


def _doctor(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", "doctor", *args], capture_output=True, text=True,
                          timeout=120)


def _lines(res: subprocess.CompletedProcess) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for ln in res.stdout.splitlines():
        parts = ln.split(None, 2)
        if len(parts) == 3 and parts[0] in ("ok", "warn", "FAIL"):
            out.setdefault(parts[1], []).append(f"{parts[0]} {parts[2]}")
    return out


def test_doctor_checks_the_router_the_vehicle_and_its_failsafe_without_engaging_it(tmp_path) -> None:
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    rover = MavlinkRover(vehicle, init_s=0.2, ekf_position_s=0.4).start()
    cfg = tmp_path / "driver.toml"
    cfg.write_text(f'[link.mavlink]\nurl = "udpout:127.0.0.1:{rover.port}"\nrate_hz = 20\n')
    port = free_port()
    try:
        with open_session(make_config(mode="router", listen=[tcp(port)])):
            res = _doctor("--driver", str(cfg), "--link", "mavlink", "--mode", "client", "--connect", tcp(port))
        found = _lines(res)
        assert res.returncode == 0, res.stdout + res.stderr
        assert found["config"][0].startswith("ok") and found["router"][0].startswith("ok")
        assert found["tls"][0].startswith("warn") and "neither encrypted nor authenticated" in found["tls"][0]
        assert found["vehicle"][0].startswith("ok") and "answers" in found["vehicle"][0]
        assert found["failsafe"][0].startswith("warn") and "up to 3 s" in found["failsafe"][0]
        assert "FS_GCS_ENABLE=0" in found["failsafe"][0]
        assert not rover.armed and rover.mode_name == "MANUAL"  # looked at, never engaged
    finally:
        rover.stop()
    res = _doctor("--mode", "client", "--connect", tcp(free_port()))  # nothing listens there
    assert res.returncode == 1 and _lines(res)["router"][0].startswith("FAIL"), res.stdout
    assert "Traceback" not in res.stderr


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
def test_doctor_names_a_certificate_about_to_expire_and_one_of_another_ca(tmp_path) -> None:
    from bridge.tools.deploy import client_config, make_ca, make_cert, make_certs, render

    certs = tmp_path / "tls"
    make_certs(certs, ["station", "operator"], days=5)
    conf = tmp_path / "operator.json5"
    conf.write_text(render(client_config("operator", connect=f"tls/127.0.0.1:{free_port()}", certs=str(certs)), ""))
    found = _lines(_doctor("--zenoh-config", str(conf)))
    tls = found["tls"]
    assert any(t.startswith("warn") and "operator.crt" in t and "expires in" in t for t in tls), tls
    other = tmp_path / "other"
    make_ca(other)
    make_cert(other, "operator")
    shutil.copy(other / "operator.crt", certs / "operator.crt")  # a certificate from another lab's CA
    tls = _lines(_doctor("--zenoh-config", str(conf)))["tls"]
    assert any(t.startswith("FAIL") and "not signed by the CA" in t for t in tls), tls


def test_doctor_fails_a_can_bus_where_no_controller_answers_and_passes_one_where_both_do() -> None:
    """Found: ``doctor --link can`` said "ok vehicle: the vehicle answers (axes idle)" on a bus with no controller
    at all; only ``engage`` said "no heartbeat". A real python-can virtual bus, the emulated ODrives or nothing."""
    import uuid

    from bridge.tools.doctor import check_vehicle
    from drivers.can.config import CanLinkConfig
    from sim_learner.can_ecu import DiffDriveEcus

    channel = f"doctor-{uuid.uuid4().hex[:8]}"
    cfg = CanLinkConfig(interface="virtual", channel=channel, heartbeat_timeout=0.3)
    silent = check_vehicle("can", cfg, max_drive_on=1.0)
    assert silent[0].level == "FAIL" and silent[0].name == "vehicle", silent
    assert "does not answer" in silent[0].text and "no heartbeat" in silent[0].text, silent
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    with DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle):
        found = check_vehicle("can", cfg, max_drive_on=1.0)
    assert found[0].level == "ok" and "answers" in found[0].text and "idle" in found[0].text, found


def test_doctor_checks_the_state_directory_and_each_robots_latch(tmp_path, monkeypatch) -> None:
    """Issue 31: ``doctor`` did not look at the state directory, where the estop latch is kept. It names the one in
    use and fails one that cannot be created (or take a file: the suite runs as root, which a read-only chmod does
    not stop, so a path under a regular file stands for it); warns a directory others may read, a fresh one ("first
    start in this state directory: no estop history"), a latch a host would start with, and a latch file not
    written by the host; passes a release its own host saved."""
    from bridge.core import wire as M
    from bridge.nodes.latch_store import Latch, latch_marker
    from bridge.tools.doctor import check_state

    (tmp_path / "file").write_text("not a directory")
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(tmp_path / "file" / "state"))
    found = check_state("r1")
    assert [c.level for c in found] == ["FAIL"] and "cannot be created" in found[0].text, found
    state = tmp_path / "state"
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(state))
    found = check_state("r1")
    assert found[0].level == "warn" and "first start in this state directory: no estop history" in found[0].text
    state.mkdir(mode=0o755)
    state.chmod(0o755)
    found = {c.name: c for c in check_state("r1")}
    assert found["state"].level == "warn" and "mode 755" in found["state"].text, found
    assert found["latch"].level == "warn" and "no estop history" in found["latch"].text, found
    state.chmod(0o700)
    latch = state / "estop-r1.bin"
    with _host(latch) as host:  # the first start: marker and a released latch, signed
        pass
    found = {c.name: c for c in check_state("r1")}
    assert found["state"].level == "ok" and str(state) in found["state"].text, found
    assert found["latch"].level == "ok" and "released" in found["latch"].text, found
    latch.write_bytes(M.encode(Latch(latched=False, source="operator")))  # someone else's "released"
    found = {c.name: c for c in check_state(None)}  # every robot with a latch in the directory
    assert found["latch"].level == "warn" and "r1: a driver host starting now is latched" in found["latch"].text
    assert "not signed by this host" in found["latch"].text, found
    latch.unlink()
    found = {c.name: c for c in check_state("r1")}
    assert found["latch"].level == "warn" and "missing" in found["latch"].text, found
    assert latch_marker(latch).exists() and host.latch.fresh_state


class _host:
    """A driver host (its link never opened) started and stopped on ``latch``."""

    def __init__(self, latch) -> None:
        from bridge.nodes.driver_config import load_driver
        from bridge.nodes.driver_host import DriverHost
        from drivers import open_driver

        cfg = load_driver(None)
        self.host = DriverHost(cfg, "udp", open_driver("udp"), "r1", 50.0, latch_path=latch)

    def __enter__(self):
        return self.host

    def __exit__(self, *exc) -> None:
        assert self.host.latch.close(5.0)


def test_doctor_warns_a_link_anyone_on_the_network_can_drive(tmp_path) -> None:
    """``doctor --driver F --link udp`` with ``insecure = true`` (and ``--link mavlink`` without a signing key)
    warns: "link unauthenticated: anyone on the network can drive it"; a keyed link passes."""
    from bridge.tools.doctor import check_auth
    from drivers.mavlink.config import MavlinkLinkConfig
    from drivers.udp import UdpLinkConfig

    for link, cfg in (("udp", UdpLinkConfig(insecure=True)), ("mavlink", MavlinkLinkConfig())):
        found = check_auth(link, cfg)
        assert [c.level for c in found] == ["warn"], found
        assert "link unauthenticated: anyone on the network can drive it" in found[0].text, found
        assert f"scmbridge keys {link}" in found[0].text, found
    assert [c.level for c in check_auth("udp", UdpLinkConfig(key_file="/k"))] == ["ok"]
    assert check_auth("can", object()) == []
    # the command: a real router and the emulated UDP robot, the link opened and never engaged
    from bridge.tools.procs import free_udp_port
    from sim_learner.udp_robot import UdpRobot

    bind = free_udp_port()
    robot = UdpRobot(SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic()), peer=("127.0.0.1", bind)).start()
    cfg = tmp_path / "driver.toml"
    cfg.write_text(f"[link.udp]\ninsecure = true\nrobot_port = {robot.port}\nbind_port = {bind}\n")
    port = free_port()
    try:
        with open_session(make_config(mode="router", listen=[tcp(port)])):
            res = _doctor("--driver", str(cfg), "--link", "udp", "--mode", "client", "--connect", tcp(port),
                          "--duration", "0.5")
    finally:
        robot.stop()
    found = _lines(res)
    assert found["auth"][0].startswith("warn") and "insecure = true" in found["auth"][0], res.stdout
    assert found["vehicle"][0].startswith("ok"), res.stdout
    assert "state" in found and "Traceback" not in res.stderr, res.stdout + res.stderr


def test_doctor_flags_latch_files_deleted_copied_back_or_foreign(tmp_path, monkeypatch) -> None:
    """Finding: a copied-back older release, a replaced marker, or marker and latch deleted together each let the
    robot drive after a restart, and ``doctor`` said "ok" or nothing. It now names each."""
    import shutil

    from bridge.nodes.latch_store import latch_marker
    from bridge.tools.doctor import check_state

    state = tmp_path / "state"
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(state))
    latch = state / "estop-r1.bin"
    with _host(latch):
        pass
    first = tmp_path / "released-copy.bin"
    shutil.copy(latch, first)
    with _host(latch) as host:  # a later start latches and releases: the record's count moves on
        from tests.integration.test_driver_host_latch import _estop

        _estop(host)
        _estop(host, engaged=False)
    assert {c.name: c for c in check_state("r1")}["latch"].level == "ok"
    shutil.copy(first, latch)  # the older release copied back
    found = {c.name: c for c in check_state("r1")}
    assert found["latch"].level == "warn" and "copied back" in found["latch"].text, found
    latch_marker(latch).write_text("11" * 32 + "\n")  # a marker of another key
    found = {c.name: c for c in check_state("r1")}
    assert found["latch"].level == "warn" and "another key" in found["latch"].text, found
    latch.unlink()
    latch_marker(latch).unlink()  # both deleted: not a first start
    found = {c.name: c for c in check_state(None)}
    assert found["latch"].level == "warn" and "deleted" in found["latch"].text, found
    assert "no estop history" not in found["latch"].text


def test_doctor_says_whether_the_stations_files_are_its_own(tmp_path, monkeypatch) -> None:
    """Finding: a mission file rewritten while the station was down, and doctor said nothing. The station's files
    carry its tag (bridge/nodes/station_tags.py); doctor checks it without making a key."""
    from bridge.core.paths import save_atomic
    from bridge.nodes.station_tags import FileTags
    from bridge.tools.doctor import check_state

    state = tmp_path / "state"
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(state))
    f = state / "mission-r1.bin"
    save_atomic(f, b"untagged")
    found = [c for c in check_state("r1") if c.name == "station"]
    assert found and found[0].level == "warn" and "no station key" in found[0].text, found
    save_atomic(f, FileTags().seal("control", f, b"payload"))
    found = [c for c in check_state("r1") if c.name == "station"]
    assert found[0].level == "ok", found
    save_atomic(f, f.read_bytes()[:-1] + b"X")  # changed while the station was down
    found = [c for c in check_state("r1") if c.name == "station"]
    assert found[0].level == "warn" and "does not verify" in found[0].text, found
