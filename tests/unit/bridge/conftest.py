"""Fixtures of the bridge's unit tests that several files share."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh


@dataclass(frozen=True)
class Certs:
    """A throwaway lab CA (``lab/ca.crt``) with a certificate per name, and another CA (``other/``) with one for
    ``rover1``: what ``scmbridge deploy certs`` makes, read back by :mod:`bridge.nodes.tlsid`."""

    lab: Path
    other: Path

    def client(self, name: str, *, issued_by: Path | None = None, trusts: Path | None = None) -> zenoh.Config:
        """A client configuration presenting ``name``'s certificate (of ``issued_by``, default the lab's CA) and
        trusting ``trusts``'s CA (default the lab's). Nothing is opened."""
        d, ca = issued_by or self.lab, trusts or self.lab
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("transport/link/protocols", '["tls"]')
        conf.insert_json5("transport/link/tls", json.dumps({
            "root_ca_certificate": str(ca / "ca.crt"), "connect_certificate": str(d / f"{name}.crt"),
            "connect_private_key": str(d / f"{name}.key"), "enable_mtls": True}))
        return conf


#: the names the lab's CA certifies: the default roles, a robot, and one the default rules do not name
LAB_NAMES = ("station", "operator", "observer", "rover1", "visitor")


@pytest.fixture(scope="session")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Certs:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: the throwaway CA and certificates are made with it")
    from bridge.tools import deploy

    d = tmp_path_factory.mktemp("certs")
    deploy.make_ca(d / "lab", cn="scmbridge test lab CA")
    for name in LAB_NAMES:
        deploy.make_cert(d / "lab", name, days=1)
    deploy.make_ca(d / "other", cn="another lab CA")
    deploy.make_cert(d / "other", "rover1", days=1)
    return Certs(d / "lab", d / "other")
