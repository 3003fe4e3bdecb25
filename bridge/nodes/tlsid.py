"""Who a Zenoh configuration says this process is: the TLS certificate it presents, and the CA it trusts.

Under the lab's mutual TLS the router knows a client by its certificate's common name (CN) and drops, silently,
whatever its access control denies: Zenoh tells the client nothing (docs/ARCHITECTURE.md, "Zenoh"). The tools read
their own identity here so that they can say *why* nothing answered: "denied: identity observer
may not engage" (:mod:`bridge.tools.identity`), or, when the session does not open at all, "the router refuses this
certificate: it was issued by CA X, the lab's CA is Y". Read with ``openssl`` (as ``scmbridge doctor`` does); every
function returns None or says nothing when it cannot tell (no TLS, no openssl, an unreadable file): a hint, never a
new way to fail.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import zenoh


@dataclass(frozen=True)
class Identity:
    """This process's TLS identity as its Zenoh configuration names it."""

    cn: str  #: the certificate's common name: what the router's access control knows this process by
    issuer: str  #: the common name of the CA that issued it
    certificate: str  #: the certificate's path
    ca_file: str | None  #: the CA certificate this configuration trusts (the lab's)
    ca_cn: str | None  #: that CA's common name
    signed_by_ca: bool | None  #: whether ``ca_file`` verifies the certificate (None: not checked)


def _json(conf: zenoh.Config, key: str) -> object:
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # a key the config does not have
        return None


def _cn(name: str) -> str:
    """The CN of an openssl ``-nameopt RFC2253`` name (``CN=operator,O=lab``), or the whole name without one."""
    m = re.search(r"(?:^|,)CN=((?:\\.|[^,])*)", name)
    return (m.group(1) if m else name).replace("\\", "").strip()


def cert_names(path: str) -> tuple[str, str] | None:
    """(subject CN, issuer CN) of the certificate at ``path``, or None when it cannot be read."""
    exe = shutil.which("openssl")
    if exe is None or not Path(path).is_file():
        return None
    try:
        res = subprocess.run([exe, "x509", "-in", path, "-noout", "-subject", "-issuer", "-nameopt", "RFC2253"],
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    if res.returncode != 0:
        return None
    fields = dict(line.split("=", 1) for line in res.stdout.strip().splitlines() if "=" in line)
    if "subject" not in fields or "issuer" not in fields:
        return None
    return _cn(fields["subject"]), _cn(fields["issuer"])


def _verifies(ca: str, path: str) -> bool | None:
    exe = shutil.which("openssl")
    if exe is None:
        return None
    try:
        res = subprocess.run([exe, "verify", "-CAfile", ca, path], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return res.returncode == 0


def identity(conf: zenoh.Config) -> Identity | None:
    """The certificate a client configuration presents (``connect_certificate``), or None: no TLS, no client
    certificate, or one that cannot be read."""
    tls = _json(conf, "transport/link/tls")
    if not isinstance(tls, dict):
        return None
    cert = tls.get("connect_certificate")
    if not isinstance(cert, str) or not cert:
        return None
    names = cert_names(cert)
    if names is None:
        return None
    ca = tls.get("root_ca_certificate") if isinstance(tls.get("root_ca_certificate"), str) else None
    ca_names = cert_names(ca) if ca else None
    signed = _verifies(ca, cert) if ca and Path(ca).is_file() else None
    return Identity(cn=names[0], issuer=names[1], certificate=cert, ca_file=ca,
                    ca_cn=ca_names[0] if ca_names else None, signed_by_ca=signed)


def refused_because(conf: zenoh.Config) -> str:
    """Why a TLS router may have refused this configuration's session, in words ("" when nothing can be told):
    a certificate another CA issued than the one this configuration trusts (the lab's) is refused by the router."""
    me = identity(conf)
    if me is None:
        return ""
    if me.signed_by_ca is False:
        lab = f"CA {me.ca_cn!r}" if me.ca_cn else me.ca_file
        return (f"the router refuses this certificate ({me.certificate}, CN {me.cn!r}): it was issued by CA "
                f"{me.issuer!r}, the lab's (the CA this configuration trusts, {me.ca_file}) is {lab}; use a "
                "certificate of the lab's CA")
    return ""
