"""bridge/tools/doctor.py: its checks as functions (docs/ARCHITECTURE.md, "Operating"): one :class:`Check` line
each, on real Zenoh configurations, real certificates (tests/unit/bridge/conftest.py's throwaway CA), a temporary
state directory and the machine's own network interfaces. The command against a router and a vehicle, the state
directory's latches as a driver host leaves them, and the link authentication warnings are in
tests/integration/test_doctor.py."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import zenoh

from bridge.tools import deploy
from bridge.tools.doctor import Check, _probe, check_access, check_auth, check_can, check_state, check_tls


def _conf(obj: dict) -> zenoh.Config:
    return zenoh.Config.from_json5(json.dumps(obj))


def test_a_check_is_one_aligned_line() -> None:
    assert Check("ok", "tls", "fine").line() == "ok    tls      fine"
    assert Check("FAIL", "vehicle", "x").line() == "FAIL  vehicle  x"


def test_access_control_is_named_counted_or_its_absence_warned() -> None:
    acl = deploy.access_control(["r1"])
    on = check_access(_conf({"mode": "router", "access_control": acl}))
    assert on.level == "ok" and f"default deny: {len(acl['rules'])} rules, {len(acl['subjects'])} subjects" in on.text
    off = check_access(_conf({"mode": "router"}))
    assert off.level == "warn" and "anyone who reaches it may publish commands" in off.text
    client = check_access(_conf({"mode": "client"}))
    assert client.level == "ok" and "the router's rules apply" in client.text


def test_no_tls_is_a_warning_that_says_who_may_drive() -> None:
    (found,) = check_tls(zenoh.Config(), 14.0)
    assert found.level == "warn" and "no TLS" in found.text and "release estops" in found.text


needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")


@needs_openssl
def test_a_client_with_the_labs_certificates_passes_and_expiry_is_warned(certs) -> None:
    conf = _conf(deploy.client_config("rover1", connect="tls/127.0.0.1:7447", certs=certs.lab))
    found = check_tls(conf, expiry_days=0.5)  # the test's certificates last a day
    assert [c.level for c in found] == ["ok", "ok"], found  # the CA and rover1's certificate; keys only exist
    assert all("valid until" in c.text for c in found)
    soon = check_tls(conf, expiry_days=30.0)
    assert {c.level for c in soon} == {"warn"} and all("expires in" in c.text for c in soon), soon


@needs_openssl
def test_missing_files_a_non_certificate_and_another_cas_certificate_fail(certs, tmp_path: Path) -> None:
    d = tmp_path / "tls"
    d.mkdir()
    shutil.copy(certs.lab / "ca.crt", d / "ca.crt")
    conf = _conf(deploy.client_config("rover1", connect="tls/127.0.0.1:7447", certs=d))
    found = check_tls(conf, 0.5)
    assert sorted(c.text for c in found if c.level == "FAIL") == [
        f"connect_certificate {d}/rover1.crt: no such file", f"connect_private_key {d}/rover1.key: no such file"]
    (d / "rover1.crt").write_text("not a certificate\n")
    (d / "rover1.key").write_text("")
    bad = [c for c in check_tls(conf, 0.5) if c.level == "FAIL"]
    assert len(bad) == 1 and "rover1.crt: not a certificate" in bad[0].text
    shutil.copy(certs.other / "rover1.crt", d / "rover1.crt")  # issued by another lab's CA
    (other,) = [c for c in check_tls(conf, 0.5) if c.level == "FAIL"]
    assert "is not signed by the CA" in other.text and "another lab CA" in other.text, other


def test_a_link_that_is_not_socketcan_has_no_device_to_check() -> None:
    assert check_can("vcan-test", "virtual") == Check("ok", "can", "interface virtual (no SocketCAN device to check)")


def test_a_missing_socketcan_interface_fails_with_the_command_that_brings_one_up() -> None:
    name = "scmnocan9"
    assert not Path(f"/sys/class/net/{name}").exists()
    found = check_can(name, "socketcan")
    assert found.level == "FAIL" and f"no CAN interface {name}" in found.text
    assert f"sudo ip link set {name} up type can bitrate 500000" in found.text


@pytest.mark.skipif(not Path("/sys/class/net/lo/operstate").exists(), reason="no sysfs network interfaces")
def test_an_interface_whose_state_is_up_or_unknown_passes() -> None:
    # the loopback device reports "unknown", as many CAN adapters do when up
    state = Path("/sys/class/net/lo/operstate").read_text().strip()
    found = check_can("lo", "socketcan")
    assert found.level == ("ok" if state in ("up", "unknown") else "FAIL"), (state, found)


def test_the_probe_leaves_nothing_behind_and_fails_where_nothing_can_be_written(tmp_path: Path) -> None:
    _probe(tmp_path)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OSError):
        _probe(tmp_path / "missing")


def test_a_state_path_that_is_a_file_fails(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "state").write_text("")
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(tmp_path / "state"))
    assert check_state(None) == [Check("FAIL", "state", f"state directory {tmp_path / 'state'} is not a directory")]


def test_a_private_state_directory_without_latches_is_ok_and_names_itself(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    d = tmp_path / "state"
    d.mkdir(mode=0o700)
    os.chmod(d, 0o700)
    monkeypatch.setenv("SCMBRIDGE_STATE_DIR", str(d))
    assert check_state(None) == [Check("ok", "state", f"state directory {d} (0700, writable)")]
    (only,) = [c for c in check_state("r9") if c.name == "latch"]  # a named robot without a latch: a fresh start
    assert only.level == "warn" and only.text.startswith("r9: first start in this state directory")
    assert list(d.iterdir()) == []  # looking wrote nothing


def test_the_state_directory_comes_from_systemd_when_scmbridges_own_variable_is_unset(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SCMBRIDGE_STATE_DIR")
    monkeypatch.setenv("STATE_DIRECTORY", f"{tmp_path / 'unit'}:{tmp_path / 'other'}")
    (found,) = check_state(None)
    assert found.level == "warn" and f"state directory {tmp_path / 'unit'} does not exist yet" in found.text


def test_a_plugin_links_authentication_warning_names_no_fix_it_does_not_know() -> None:
    class Quiet:
        def unauthenticated(self) -> str:
            return "no key"

    (found,) = check_auth("loopback", Quiet())  # a plugin link: no known fix to print
    assert found == Check("warn", "auth", "link loopback: no key: link unauthenticated: anyone on the network can "
                                          "drive it")
