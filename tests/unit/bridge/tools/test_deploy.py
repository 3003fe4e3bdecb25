"""bridge/tools/deploy.py: the pure generators of ``scmbridge deploy`` (docs/ARCHITECTURE.md, "Zenoh";
deploy/README.md): rule and name checks, the access control's structure, the router's and clients' configs, the
JSON5 rendering and the subjectAltName helper. What each identity may do by the generated rules, and those rules
enforced by a real router, are in tests/integration/test_zenoh_acl.py; the shipped files and certificates in
tests/integration/test_deploy.py."""

from __future__ import annotations

import json

import pytest

from bridge.core import wire as M
from bridge.tools import deploy


def _json5(text: str) -> dict:
    """The config of a rendered file: its ``//`` header lines dropped, the rest is plain JSON."""
    return json.loads("\n".join(ln for ln in text.splitlines() if not ln.startswith("//")))


def test_a_rule_allows_one_flow_only() -> None:
    r = deploy._rule("x/y", "egress", ("put",), iter(["scm/a/cmd"]))
    assert r == {"id": "x/y", "permission": "allow", "flows": ["egress"], "messages": ["put"],
                 "key_exprs": ["scm/a/cmd"]}
    with pytest.raises(ValueError, match="flow must be ingress or egress, not 'both'"):
        deploy._rule("x", "both", ["put"], [])


@pytest.mark.parametrize(("robots", "names", "match"), [
    ([], ("station", "operator"), "at least one robot"),
    (["r1"], ("station", ""), "plain non-empty name"),
    (["r1"], ("sta/tion", "operator"), "plain non-empty name"),
    (["r1"], ("station", 'op"erator'), "plain non-empty name"),
    (["r1", "r1"], ("station", "operator"), "repeated: r1"),
    (["r1"], ("station", "station"), "repeated: station"),
    (["r1"], ("station", "operator", "r1"), "repeated: r1"),
])
def test_identity_names_are_checked(robots: list[str], names: tuple[str, ...], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        deploy._check_names(robots, *names)


def test_every_policy_names_existing_rules_and_each_rule_belongs_to_one_policy() -> None:
    acl = deploy.access_control(["r1", "r2"], mocap_cn="mocap", teacher_cn="teacher")
    ids = [r["id"] for r in acl["rules"]]
    assert len(ids) == len(set(ids))  # rule ids are unique
    in_policies = [rid for p in acl["policies"] for rid in p["rules"]]
    assert sorted(in_policies) == sorted(ids)
    subjects = {s["id"] for s in acl["subjects"]}
    assert {s for p in acl["policies"] for s in p["subjects"]} == subjects
    assert subjects == {"robot/r1", "robot/r2", "station", "operator", "observer", "mocap", "teacher"}


def test_without_an_observer_there_is_no_observer_identity() -> None:
    acl = deploy.access_control(["r1"], observer_cn=None)
    assert "observer" not in {s["id"] for s in acl["subjects"]}
    assert not [r for r in acl["rules"] if r["id"].startswith("observer/")]
    # then "observer" may even be a robot's name: it is no identity of its own
    assert "robot/observer" in {s["id"] for s in deploy.access_control(["observer"], observer_cn=None)["subjects"]}


def test_each_robot_gets_the_same_rules_on_its_own_keys() -> None:
    acl = deploy.access_control(["r1", "r2"])

    def mine(robot: str) -> list[tuple[str, list[str]]]:
        return [(r["id"].split("/", 2)[2], [k.replace(robot, "R") for k in r["key_exprs"]])
                for r in acl["rules"] if r["id"].startswith(f"robot/{robot}/")]

    assert mine("r1") == mine("r2") and mine("r1")
    assert ("alive", [M.alive_key("R", "driver")]) in mine("r1")


def test_the_router_config_is_mutual_tls_on_the_lab_address_with_the_stations_identity() -> None:
    conf = deploy.router_config(["r1"], listen="tls/10.0.0.5:7447", certs="/srv/tls/", station_cn="base")
    assert conf["mode"] == "router" and conf["listen"] == {"endpoints": ["tls/10.0.0.5:7447"]}
    assert conf["connect"] == {"endpoints": []}
    assert conf["scouting"] == {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    t = conf["transport"]
    assert t["shared_memory"] == {"enabled": False} and t["link"]["protocols"] == ["tls"]
    assert t["link"]["tls"] == {"root_ca_certificate": "/srv/tls/ca.crt", "enable_mtls": True,  # no "//": stripped
                                "listen_private_key": "/srv/tls/base.key", "listen_certificate": "/srv/tls/base.crt"}
    assert {"id": "station", "cert_common_names": ["base"]} in conf["access_control"]["subjects"]


@pytest.mark.parametrize("listen", ["tls/:7447", "tls/[::]:7447", "tls/:::7447"])
def test_the_router_never_listens_on_every_interface(listen: str) -> None:
    with pytest.raises(ValueError, match="every interface"):
        deploy.router_config(["r1"], listen=listen)


def test_a_client_reaches_the_router_over_tls_checking_its_name() -> None:
    conf = deploy.client_config("r1", connect="tls/lab-router:7447", certs="/etc/x")
    assert conf["mode"] == "client" and conf["connect"] == {"endpoints": ["tls/lab-router:7447"]}
    tls = conf["transport"]["link"]["tls"]
    assert tls["connect_private_key"] == "/etc/x/r1.key" and tls["connect_certificate"] == "/etc/x/r1.crt"
    assert tls["verify_name_on_connect"] is True and tls["enable_mtls"] is True
    assert conf["transport"]["shared_memory"] == {"enabled": False}
    assert "listen" not in conf
    with pytest.raises(ValueError, match="over TLS only"):
        deploy.client_config("r1", connect="tcp/lab-router:7447")


def test_rendered_files_say_how_they_were_made_and_read_back_as_the_config() -> None:
    conf = deploy.router_config(["r1", "r2"])
    text = deploy.render(conf, "scmbridge deploy acl --robots r1,r2")
    head = text.splitlines()[: len(deploy.ROUTER_HEADER) + 1]
    assert head[:-1] == [f"// {x}" for x in deploy.ROUTER_HEADER]
    assert head[-1] == "// Generated by `scmbridge deploy acl --robots r1,r2`; regenerate it instead of editing it " \
                       "(deploy/README.md)."
    assert _json5(text) == conf and text.endswith("\n")
    client = deploy.render(deploy.client_config("r1"), "cmd", deploy.CLIENT_HEADER)
    assert client.startswith(f"// {deploy.CLIENT_HEADER[0]}\n") and _json5(client)["mode"] == "client"


def test_the_dump_keeps_lines_within_the_width_where_a_value_fits() -> None:
    conf = deploy.router_config(["r1", "r2", "r3"])
    text = deploy._dump(conf)
    assert json.loads(text) == conf
    long = [ln for ln in text.splitlines() if len(ln) > 118]
    # only a line whose one value is longer than the width itself may exceed it
    assert all(len(json.dumps(json.loads(ln.strip().rstrip(",").split(": ", 1)[-1]))) > 100 for ln in long)
    assert deploy._dump({"a": 1}) == '{"a": 1}' and deploy._dump([]) == "[]"
    nested = deploy._dump({"k": list(range(60))}, width=40)
    assert nested.startswith("{\n") and json.loads(nested) == {"k": list(range(60))}


def test_router_addresses_become_ip_or_dns_alt_names() -> None:
    assert deploy._sans(["192.168.50.10", "::1", "station.lab", "fe80::1"]) == [
        "IP:192.168.50.10", "IP:::1", "DNS:station.lab", "IP:fe80::1"]
    assert deploy._sans([]) == []


def test_comma_separated_names_drop_blanks() -> None:
    assert deploy._names(" a, b,,c , ") == ["a", "b", "c"] and deploy._names("") == []


def test_a_value_or_runtime_error_becomes_a_one_line_usage_error() -> None:
    from bridge.core.errors import UsageError

    with pytest.raises(UsageError, match="openssl is not installed"):
        deploy._or_usage(lambda: (_ for _ in ()).throw(RuntimeError("openssl is not installed")))
    with pytest.raises(UsageError, match="at least one robot"):
        deploy._or_usage(lambda: deploy.access_control([]))
    assert deploy._or_usage(lambda: 7) == 7
    with pytest.raises(KeyError):  # anything else is a bug, not the user's: not turned into a usage error
        deploy._or_usage(lambda: {}["x"])


def test_a_certificates_end_of_validity_is_read_back(certs) -> None:
    assert deploy.valid_until(certs.lab / "rover1.crt").endswith("GMT")
    assert deploy.valid_until(certs.lab / "no-such.crt") == "unknown"
