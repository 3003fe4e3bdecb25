"""Who a Zenoh configuration says this process is (:mod:`bridge.nodes.tlsid`), read with openssl from throwaway
certificates (tests/unit/bridge/conftest.py): the names of a certificate, the identity of a client configuration,
why a TLS router refuses it; and saying nothing (None, "") whenever it cannot tell. Nothing is opened: the same
identities against a real TLS router are tested in tests/integration/test_zenoh_acl.py."""

from __future__ import annotations

import json

import pytest
import zenoh

from bridge.nodes import tlsid
from bridge.nodes.tlsid import Identity, _cn, cert_names, identity, refused_because
from bridge.nodes.zsession import make_config


@pytest.mark.parametrize(("name", "cn"), [
    ("CN=operator,O=lab", "operator"),
    ("O=lab,CN=rover1", "rover1"),
    ("CN=scmbridge lab CA 1a2b", "scmbridge lab CA 1a2b"),
    (r"CN=a\,b,O=x", "a,b"),  # an escaped comma is part of the name
    ("O=lab,OU=CNx", "O=lab,OU=CNx"),  # no CN: the whole name (not a CN found inside another attribute's value)
])
def test_the_common_name_of_an_rfc2253_name(name: str, cn: str) -> None:
    assert _cn(name) == cn


def test_cert_names_are_the_subject_and_issuer_common_names(certs) -> None:
    assert cert_names(str(certs.lab / "operator.crt")) == ("operator", "scmbridge test lab CA")
    assert cert_names(str(certs.other / "rover1.crt")) == ("rover1", "another lab CA")
    assert cert_names(str(certs.lab / "ca.crt")) == ("scmbridge test lab CA", "scmbridge test lab CA")


def test_cert_names_of_what_is_no_certificate_is_none(certs, tmp_path) -> None:
    junk = tmp_path / "junk.crt"
    junk.write_text("-----BEGIN CERTIFICATE-----\nnot base64\n-----END CERTIFICATE-----\n")
    assert cert_names(str(junk)) is None
    assert cert_names(str(tmp_path / "absent.crt")) is None
    assert cert_names(str(tmp_path)) is None  # a directory
    assert cert_names(str(certs.lab / "operator.key")) is None  # a key, not a certificate


def test_without_openssl_nothing_can_be_told(certs, monkeypatch) -> None:
    monkeypatch.setattr(tlsid.shutil, "which", lambda exe: None)
    assert cert_names(str(certs.lab / "operator.crt")) is None
    assert identity(certs.client("operator")) is None and refused_because(certs.client("operator")) == ""


def test_the_identity_of_a_client_of_the_labs_ca(certs) -> None:
    me = identity(certs.client("operator"))
    assert me == Identity(cn="operator", issuer="scmbridge test lab CA", certificate=str(certs.lab / "operator.crt"),
                          ca_file=str(certs.lab / "ca.crt"), ca_cn="scmbridge test lab CA", signed_by_ca=True)
    assert refused_because(certs.client("operator")) == ""  # nothing to say: the router would take it


def test_a_certificate_of_another_ca_is_named_as_such(certs) -> None:
    conf = certs.client("rover1", issued_by=certs.other)
    me = identity(conf)
    assert me is not None and me.signed_by_ca is False and me.issuer == "another lab CA"
    why = refused_because(conf)
    assert why.startswith(f"the router refuses this certificate ({certs.other / 'rover1.crt'}, CN 'rover1'): it was "
                          "issued by CA 'another lab CA', the lab's")
    assert "is CA 'scmbridge test lab CA'" in why and why.endswith("use a certificate of the lab's CA")


def test_a_ca_file_that_is_missing_is_not_checked(certs, tmp_path) -> None:
    conf = certs.client("operator")
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tmp_path / "none.crt")))
    me = identity(conf)
    assert me is not None and me.cn == "operator" and me.ca_cn is None and me.signed_by_ca is None
    assert refused_because(conf) == ""  # never a claim it cannot see


def test_no_tls_or_no_client_certificate_is_no_identity(certs, tmp_path) -> None:
    assert identity(make_config()) is None and refused_because(make_config()) == ""
    assert identity(zenoh.Config()) is None
    conf = certs.client("operator")
    conf.insert_json5("transport/link/tls/connect_certificate", '""')
    assert identity(conf) is None
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(tmp_path / "gone.crt")))
    assert identity(conf) is None and refused_because(conf) == ""
