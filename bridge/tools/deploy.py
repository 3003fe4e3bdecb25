"""``scmbridge deploy``: generate the lab's TLS + access-control router config, and throwaway certificates.

The access control is generated from the wire contract (:mod:`bridge.core.wire`), never written by hand, so every robot
gets exactly the same rules and a new topic cannot be forgotten in one robot's block. The router (``scmbridge
router``, a process of its own on the base station: ``scmbridge-router.service``) identifies each client by the
common name (CN) of the certificate it presents over mutual TLS, and with ``default_permission: "deny"`` lets
through only what a rule allows:

* **a robot** ``R`` publishes its own ``state``, ``applied`` and ``status/driver``; it subscribes to and receives
  only its own ``cmd`` and ``estop``, and answers ``estop`` queries (its latch state) with replies on that key;
* **the station** publishes ``cmd``, ``teacher``, ``limits``, ``journal`` and its ``status/station`` for every
  robot, receives the robots' ``state``, ``applied``, ``status/driver`` and ``mission``, and answers ``pairs`` queries;
* **the operator** publishes ``estop`` (engage and release: one key) and ``mission`` (a new mission for a running
  station: only a person's identity may replace what a robot drives to; the station's certificate may not) for
  every robot, and the estop on ``scm/*/estop`` too (``estop --all``'s first stop, which every robot receives), and
  may query ``estop`` and ``pairs``;
* optionally **a motion-capture bridge** (``--mocap-cn``) publishes ``mocap`` for every robot (which each robot's
  driver host receives), and **an external teacher** (``--teacher-cn``) publishes ``teacher`` for every robot and
  receives ``state`` and ``limits`` (``[teacher] kind = "external"``);
* **any other certificate** of the lab's CA connects but gets nothing: no rule names it, so every message it
  sends or would receive is denied. A client without a certificate, with another CA's, or speaking plain TCP is
  refused by the TLS listener itself (``enable_mtls``, ``protocols: ["tls"]``).

Rules are written per direction as the router sees them: ``ingress`` is what a client sends to the router,
``egress`` what the router forwards to it. Besides the data (``put``, ``query``, ``reply``) a client's
*declarations* are filtered too: a robot cannot even declare a subscriber on another robot's ``cmd``. The router
also tells a publishing client which subscribers exist (declarations, egress), because a Zenoh 1.x client with a
declared publisher sends only when it knows of a matching subscriber; those are allowed only on the keys that
client may publish. Keys are listed one by one (no wildcards): a wildcard key expression in a rule matches only
messages whose key it includes, and exact keys are also the fastest to check. Everything else (``delete``,
liveliness, queries on the admin space ``@/**``) falls to the default, deny.

As deployed, the router is a process of its own (``scmbridge router --zenoh-config router.json5``) and the station is
its client like every other node (``station-client.json5``, the ``station`` certificate): when the station stops,
the router stays, so the operator's ``status`` and ``estop --all`` still reach every driver host. The router
presents the ``station`` certificate (the base station's, naming the addresses clients connect to) as its TLS
identity; its own session publishes nothing. The access control is read once when the router starts: Zenoh cannot
reload it, so a robot added to the fleet costs a router restart (deploy/README.md, "Adding a robot").

:func:`bridge.tools.identity.role_of` and :func:`bridge.tools.identity.denial` answer, from the same rules, whether
an identity may do something: a tool whose query nobody answered tells "denied by the access control" from "nobody
there" with them (the router drops a denied
message silently; Zenoh tells the client nothing).

``scmbridge deploy certs`` makes a CA and one certificate per name with ``openssl``, for tests and a lab's first
try. A lab should issue the certificates from its own PKI: a throwaway CA's key lying next to the certificates
is not a security boundary.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import secrets
import shutil
import subprocess
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from bridge.core import wire as M
from bridge.core.args import robots_arg
from bridge.core.errors import UsageError

#: what a robot's driver host publishes, and what it listens to (docs/ARCHITECTURE.md section 3)
ROBOT_PUBLISHES = ("state", "applied")
ROBOT_RECEIVES = ("cmd", "estop")
#: what the station publishes for each robot, and what it listens to
STATION_PUBLISHES = ("cmd", "teacher", "limits", "journal")
STATION_RECEIVES = ("state", "applied", "mission")

#: the lab address placeholder of the shipped files (deploy/README.md: replace it with the lab interface's)
LAB_LISTEN = "tls/192.168.50.10:7447"
#: where the shipped files expect the certificates on the base station
LAB_CERTS = "/etc/scmbridge/tls"


def _rule(rid: str, flow: str, messages: Sequence[str], keys: Iterable[str]) -> dict[str, Any]:
    """One ``allow`` rule of the access control: ``messages`` on ``keys`` in one ``flow``."""
    if flow not in ("ingress", "egress"):
        raise ValueError(f"flow must be ingress or egress, not {flow!r}")
    return {"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages), "key_exprs": list(keys)}


def _check_names(robots: Sequence[str], station_cn: str, operator_cn: str, *others: str) -> None:
    """Robot names are key chunks; every identity is distinct (one certificate, one role)."""
    if not robots:
        raise ValueError("at least one robot is needed")
    for r in robots:
        M.check_robot(r)
    names = [*robots, station_cn, operator_cn, *others]
    for n in (station_cn, operator_cn, *others):
        if not n or any(c in n for c in "/\\\n\r\t\"'"):
            raise ValueError(f"common name {n!r} must be a plain non-empty name")
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"each identity must have its own common name; repeated: {', '.join(dupes)}")


#: the wildcard keys operator tools ask and listen on (estop --all, status --all, view --all, record), and the
#: robots' liveliness tokens (a stalled driver host keeps its token: estop --all still finds it)
ALL_ESTOPS = f"{M.PREFIX}/*/estop"
EVERYTHING = f"{M.PREFIX}/**"
ALL_ALIVE = f"{M.PREFIX}/*/alive/**"
#: every node's status: ``scmbridge status`` asks the nodes for their last one (each node's status key is a
#: queryable too) instead of waiting for the next periodic one
ALL_STATUS = f"{M.PREFIX}/*/status/*"


def _status_queries(robot: str) -> list[str]:
    """The key expressions a status query reaching ``robot``'s nodes may carry: the fleet's and the robot's."""
    return [ALL_STATUS, f"{M.PREFIX}/{robot}/status/*"]


def _reader(role: str) -> list[dict[str, Any]]:
    """Read everything (``scm/**``), publish nothing: the observer's rights, which the operator has too."""
    return [_rule(f"{role}/subscribes-all", "ingress", ["declare_subscriber"], [EVERYTHING]),
            _rule(f"{role}/receives-all", "egress", ["put"], [EVERYTHING]),
            _rule(f"{role}/liveliness", "ingress", ["liveliness_query", "declare_liveliness_subscriber"],
                  [ALL_ALIVE]),
            _rule(f"{role}/liveliness-replies", "egress", ["liveliness_token"], [ALL_ALIVE]),
            _rule(f"{role}/status-queries", "ingress", ["query"], [ALL_STATUS]),
            _rule(f"{role}/status-replies", "egress", ["reply"], [ALL_STATUS])]


def access_control(robots: Sequence[str], *, station_cn: str = "station", operator_cn: str = "operator",
                   mocap_cn: str | None = None, teacher_cn: str | None = None,
                   observer_cn: str | None = "observer") -> dict[str, Any]:
    """The ``access_control`` section for ``robots``: default deny, one set of allow rules per identity."""
    robots = list(robots)
    _check_names(robots, station_cn, operator_cn, *(n for n in (mocap_cn, teacher_cn, observer_cn) if n))
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    for r in robots:
        k = M.Keys(r)
        pubs = [getattr(k, t) for t in ROBOT_PUBLISHES] + [M.status_key(r, "driver")]
        recv = [getattr(k, t) for t in ROBOT_RECEIVES] + ([k.mocap] if mocap_cn else [])
        rid = f"robot/{r}"  # a robot name has no "/", so these ids never collide with the station's or operator's
        mine = [
            _rule(f"{rid}/publishes", "ingress", ["put"], pubs),
            # a declared publisher sends only once it knows of a matching subscriber, also an operator's or an
            # observer's wildcard one (status --all, view, record): learning of a subscriber carries no data
            _rule(f"{rid}/publishes-matching", "egress", ["declare_subscriber"], [*pubs, EVERYTHING]),
            _rule(f"{rid}/subscribes", "ingress", ["declare_subscriber"], recv),
            # (the operator's ``estop --all`` stops every robot with one put on the wildcard key first)
            _rule(f"{rid}/receives", "egress", ["put"], [*recv, ALL_ESTOPS]),
            _rule(f"{rid}/answers-estop", "ingress", ["declare_queryable", "reply"], [k.estop, k.engage]),
            _rule(f"{rid}/estop-queries", "egress", ["query"], [k.estop, k.engage, ALL_ESTOPS]),
            _rule(f"{rid}/alive", "ingress", ["liveliness_token"], [M.alive_key(r, "driver")]),
            _rule(f"{rid}/answers-status", "ingress", ["declare_queryable", "reply"], [M.status_key(r, "driver")]),
            _rule(f"{rid}/status-queries", "egress", ["query"], [M.status_key(r, "driver"), *_status_queries(r)]),
        ]
        rules += mine
        subjects.append({"id": rid, "cert_common_names": [r]})
        policies.append({"id": rid, "subjects": [rid], "rules": [x["id"] for x in mine]})

    each = [M.Keys(r) for r in robots]
    s_pubs = [getattr(k, t) for k in each for t in STATION_PUBLISHES] + [M.status_key(r, "station") for r in robots]
    s_recv = [getattr(k, t) for k in each for t in STATION_RECEIVES] + [M.status_key(r, "driver") for r in robots]
    pairs = [k.pairs for k in each]
    estops = [k.estop for k in each]
    controls = [k.control for k in each]
    engages = [k.engage for k in each]
    missions = [k.mission for k in each]
    cmds = [k.cmd for k in each]
    station = [
        _rule("station/publishes", "ingress", ["put"], s_pubs),
        _rule("station/publishes-matching", "egress", ["declare_subscriber"], [*s_pubs, EVERYTHING]),
        _rule("station/subscribes", "ingress", ["declare_subscriber"], s_recv),
        _rule("station/receives", "egress", ["put"], s_recv),
        _rule("station/answers-pairs", "ingress", ["declare_queryable", "reply"], pairs),
        _rule("station/pairs-queries", "egress", ["query"], pairs),
        _rule("station/queries-pairs", "ingress", ["query"], pairs),
        _rule("station/pairs-replies", "egress", ["reply"], pairs),
        _rule("station/answers-control", "ingress", ["declare_queryable", "reply"], controls),
        _rule("station/control-queries", "egress", ["query"], controls),
        _rule("station/hears-cmd", "ingress", ["declare_subscriber"], cmds),  # another sender on its robot's key
        _rule("station/receives-cmd", "egress", ["put"], cmds),
        _rule("station/answers-status", "ingress", ["declare_queryable", "reply"],
              [M.status_key(r, "station") for r in robots]),
        _rule("station/status-queries", "egress", ["query"],
              [*(M.status_key(r, "station") for r in robots), ALL_STATUS,
               *(q for r in robots for q in _status_queries(r)[1:])]),
    ]
    # the operator: estop (engage and release), engage, missions (requests, and a new mission for a running station:
    # the station's certificate may not publish one), pairs, and everything an observer may read
    operator = [
        # each robot's key, and the wildcard ``estop --all`` puts first (only the operator may put it)
        _rule("operator/estop", "ingress", ["put"], [*estops, ALL_ESTOPS]),
        _rule("operator/missions", "ingress", ["put"], missions),
        _rule("operator/missions-matching", "egress", ["declare_subscriber"], missions),
        _rule("operator/estop-latches", "ingress", ["query"], [*estops, ALL_ESTOPS]),
        _rule("operator/estop-matching", "egress", ["declare_subscriber", "declare_queryable"], estops),
        _rule("operator/estop-replies", "egress", ["reply"], estops),
        _rule("operator/queries", "ingress", ["query"], [*pairs, *controls, *engages]),
        _rule("operator/replies", "egress", ["reply"], [*pairs, *controls, *engages]),
        *_reader("operator"),
    ]
    roles = {"station": (station_cn, station), "operator": (operator_cn, operator)}
    if observer_cn:  # reads everything, asks only what changes nothing (pairs, the estop latch), publishes nothing
        roles["observer"] = (observer_cn, [
            *_reader("observer"),
            _rule("observer/queries", "ingress", ["query"], [*pairs, *estops, ALL_ESTOPS]),
            _rule("observer/replies", "egress", ["reply"], [*pairs, *estops])])
    if mocap_cn:
        mocaps = [k.mocap for k in each]
        roles["mocap"] = (mocap_cn, [_rule("mocap/publishes", "ingress", ["put"], mocaps),
                                     _rule("mocap/publishes-matching", "egress", ["declare_subscriber"], mocaps)])
    if teacher_cn:
        teach = [k.teacher for k in each]
        seen = [k.state for k in each] + [k.limits for k in each]
        roles["teacher"] = (teacher_cn, [
            _rule("teacher/publishes", "ingress", ["put"], teach),
            _rule("teacher/publishes-matching", "egress", ["declare_subscriber"], teach),
            _rule("teacher/subscribes", "ingress", ["declare_subscriber"], seen),
            _rule("teacher/receives", "egress", ["put"], seen)])
    for role, (cn, mine) in roles.items():
        rules += mine
        subjects.append({"id": role, "cert_common_names": [cn]})
        policies.append({"id": role, "subjects": [role], "rules": [x["id"] for x in mine]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _transport(certs_dir: str, **tls: Any) -> dict[str, Any]:
    """TLS only, mutual, trusting ``<certs_dir>/ca.crt`` (``tls``: this side's key and certificate), and no
    shared-memory transport: a same-machine sender's pool otherwise stays mapped in every receiver after the sender
    has gone (docs/ARCHITECTURE.md, "Zenoh")."""
    return {
        "link": {"protocols": ["tls"],
                 "tls": {"root_ca_certificate": f"{certs_dir}/ca.crt", "enable_mtls": True, **tls}},
        "shared_memory": {"enabled": False},
    }


def router_config(robots: Sequence[str], *, station_cn: str = "station", operator_cn: str = "operator",
                  listen: str = LAB_LISTEN, certs: str | Path = LAB_CERTS, mocap_cn: str | None = None,
                  teacher_cn: str | None = None, observer_cn: str | None = "observer") -> dict[str, Any]:
    """The base station's router config: mutual TLS only on ``listen``, no scouting, the generated access control.

    The router presents the station's certificate (``<certs>/<station_cn>.crt``) and accepts only clients whose
    certificate the CA in ``<certs>/ca.crt`` signed.
    """
    if not listen.startswith("tls/"):
        raise ValueError(f"the router listens on TLS only: --listen must be tls/ADDR:PORT, not {listen!r}")
    host = listen[4:].rsplit(":", 1)[0]
    if host in ("0.0.0.0", "[::]", "::", ""):
        raise ValueError(f"listen on the lab interface's address, not on every interface ({listen!r})")
    d = str(certs).rstrip("/")
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": _transport(d, listen_private_key=f"{d}/{station_cn}.key",
                                listen_certificate=f"{d}/{station_cn}.crt"),
        "access_control": access_control(robots, station_cn=station_cn, operator_cn=operator_cn, mocap_cn=mocap_cn,
                                         teacher_cn=teacher_cn, observer_cn=observer_cn),
    }


def client_config(name: str, *, connect: str = LAB_LISTEN, certs: str | Path = LAB_CERTS) -> dict[str, Any]:
    """A client's config (a robot's driver host, a station-side tool, the operator's console): mutual TLS to the
    router at ``connect`` with ``<certs>/<name>.key`` and ``<certs>/<name>.crt``, trusting ``<certs>/ca.crt``.

    The client checks the router's certificate against the address in ``connect`` (``verify_name_on_connect``), so
    the station's certificate must name that address (``scmbridge deploy certs --station-address``).
    """
    if not connect.startswith("tls/"):
        raise ValueError(f"clients reach the router over TLS only: --connect must be tls/ADDR:PORT, not {connect!r}")
    d = str(certs).rstrip("/")
    return {
        "mode": "client",
        "connect": {"endpoints": [connect]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": _transport(d, connect_private_key=f"{d}/{name}.key", connect_certificate=f"{d}/{name}.crt",
                                verify_name_on_connect=True),
    }


ROUTER_HEADER = (
    "Lab network with mutual TLS and access control on the lab's router (scmbridge router, scmbridge-router.service).",
    "Default deny: a robot publishes only its own state/applied/status/driver and receives only its own cmd/estop;",
    "the station publishes cmd/teacher/limits; the operator publishes estop/mission; a certificate not named below",
    "connects but neither sends nor receives anything.",
)
CLIENT_HEADER = (
    "Lab network with mutual TLS, a client of the base station's router (a robot's driver host, or the operator).",
    "If the link drops, the driver host's deadman stops the robot within cmd_timeout; the client reconnects.",
)


def render(config: dict[str, Any], command: str, header: Sequence[str] = ROUTER_HEADER) -> str:
    """JSON5 text of ``config`` (plain JSON is JSON5) under comments saying what it is and how it was made."""
    lines = [f"// {x}" for x in header]
    lines.append(f"// Generated by `{command}`; regenerate it instead of editing it (deploy/README.md).")
    return "\n".join(lines) + "\n" + _dump(config) + "\n"


def _dump(obj: Any, indent: str = "", used: int = 0, width: int = 118) -> str:
    """JSON, each value on one line where it fits in ``width`` (``used``: columns taken before it), nested
    otherwise: a rule reads as a few lines, not one line per key."""
    flat = json.dumps(obj)
    if len(indent) + used + len(flat) <= width or not isinstance(obj, (dict, list)) or not obj:
        return flat
    inner = indent + "  "
    if isinstance(obj, dict):
        items = [f"{inner}{json.dumps(k)}: {_dump(v, inner, len(json.dumps(k)) + 2, width)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    return "[\n" + ",\n".join(inner + _dump(v, inner, 0, width) for v in obj) + "\n" + indent + "]"


# ----------------------------------------------------------------------------------------------- certificates
_EC = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]


def _openssl(args: Sequence[str]) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise RuntimeError("openssl is not installed (apt-get install openssl)")
    res = subprocess.run([exe, *args], capture_output=True, text=True, timeout=60)
    if res.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {res.stderr.strip()}")


def make_ca(out: Path, *, cn: str | None = None, days: int = 30) -> None:
    """A throwaway CA (``ca.key``, ``ca.crt``) in ``out``: EC P-256, valid ``days``. A new ``out`` is made
    private (0700) so no key is readable by others even before it is chmod-ed 0600.

    Each CA gets its own name (``scmbridge lab CA <random id>``, unless ``cn``): a certificate of another lab's CA
    is then named as such by the tools and ``scmbridge doctor`` ("issued by CA X, this configuration trusts CA Y"),
    where one name for every CA would make them look alike."""
    cn = cn or f"scmbridge lab CA {secrets.token_hex(4)}"
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    _openssl(["req", "-x509", *_EC, "-keyout", str(out / "ca.key"), "-out", str(out / "ca.crt"), "-days", str(days),
              "-subj", f"/CN={cn}", "-addext", "basicConstraints=critical,CA:TRUE",
              "-addext", "keyUsage=critical,keyCertSign,cRLSign"])
    (out / "ca.key").chmod(0o600)


def make_cert(out: Path, name: str, *, sans: Sequence[str] = (), days: int = 30, ca_dir: Path | None = None) -> None:
    """``<name>.key`` and ``<name>.crt`` (CN = ``name``) signed by the CA in ``ca_dir`` (default ``out``).

    ``sans`` are subjectAltName entries (``IP:192.168.50.10``, ``DNS:station``): a client checks the router's
    certificate against the address it connects to, so the station's certificate carries the router's address.
    The certificate serves as client and as server (the station's is both).
    """
    ca = out if ca_dir is None else ca_dir
    key, csr, crt, ext = (out / f"{name}.{x}" for x in ("key", "csr", "crt", "ext"))
    _openssl(["req", "-new", *_EC, "-keyout", str(key), "-out", str(csr), "-subj", f"/CN={name}"])
    key.chmod(0o600)
    lines = ["basicConstraints=critical,CA:FALSE", "keyUsage=critical,digitalSignature",
             "extendedKeyUsage=serverAuth,clientAuth", "subjectAltName=" + ",".join([f"DNS:{name}", *sans])]
    ext.write_text("\n".join(lines) + "\n")
    try:
        _openssl(["x509", "-req", "-in", str(csr), "-CA", str(ca / "ca.crt"), "-CAkey", str(ca / "ca.key"),
                  "-CAcreateserial", "-out", str(crt), "-days", str(days), "-extfile", str(ext)])
    finally:
        csr.unlink(missing_ok=True)
        ext.unlink(missing_ok=True)


def make_certs(out: Path, names: Sequence[str], *, station_cn: str = "station",
               station_sans: Sequence[str] = ("IP:127.0.0.1",), days: int = 30) -> list[str]:
    """A CA (kept if ``out`` has one: a new CA would break every robot already deployed) and a certificate for
    each name that has none yet; the station's carries ``station_sans``. Returns what it did, one line each."""
    done = []
    if (out / "ca.crt").exists() and (out / "ca.key").exists():
        done.append(f"kept the CA in {out} (valid until {valid_until(out / 'ca.crt')})")
    else:
        make_ca(out, days=max(days, 365))
        done.append(f"made a CA in {out} (valid until {valid_until(out / 'ca.crt')})")
    for n in names:
        crt = out / f"{n}.crt"
        if crt.exists():
            done.append(f"kept {crt} (valid until {valid_until(crt)})")
            continue
        make_cert(out, n, sans=station_sans if n == station_cn else (), days=days)
        done.append(f"made {crt} (valid until {valid_until(crt)})")
    return done


def valid_until(crt: Path) -> str:
    """The certificate's end of validity, as openssl prints it."""
    exe = shutil.which("openssl")
    res = subprocess.run([exe or "openssl", "x509", "-in", str(crt), "-noout", "-enddate"], capture_output=True,
                         text=True, timeout=30)
    return res.stdout.strip().split("=", 1)[-1] or "unknown"


# ------------------------------------------------------------------------------------------------------- CLI
def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def _sans(addresses: Sequence[str]) -> list[str]:
    """subjectAltName entries for the router's addresses: ``IP:`` for an IPv4/IPv6 address, else ``DNS:``."""
    out = []
    for a in addresses:
        try:
            ipaddress.ip_address(a)
            out.append(f"IP:{a}")
        except ValueError:
            out.append(f"DNS:{a}")
    return out


def arguments_acl(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--robots", type=robots_arg, required=True,
                    help="comma-separated robot names (= their certificates' CN)")
    ap.add_argument("--station-cn", default="station", help="the station's certificate CN (default station)")
    ap.add_argument("--operator-cn", default="operator", help="the operator's certificate CN (default operator)")
    ap.add_argument("--mocap-cn", default=None, help="a motion-capture bridge's CN (may publish every robot's mocap)")
    ap.add_argument("--teacher-cn", default=None, help="an external teacher's CN (publishes teacher, sees state "
                                                       "and limits)")
    ap.add_argument("--observer-cn", default="observer",
                    help="the observer's CN: reads everything (view, record, status, pairs), publishes nothing "
                         "(default observer; empty: no observer)")
    ap.add_argument("--listen", default=LAB_LISTEN, help=f"router endpoint tls/ADDR:PORT (default {LAB_LISTEN})")
    ap.add_argument("--certs", default=LAB_CERTS,
                    help=f"directory of ca.crt and the station's key and certificate (default {LAB_CERTS})")


def run_acl(args: argparse.Namespace) -> int:
    """Print the lab router's Zenoh config (JSON5), for scmbridge router (scmbridge-router.service reads
    /etc/scmbridge/router.json5): mutual TLS only, no scouting, and the access control generated from the wire
    contract for the given robots (default deny). The router reads it once at start: a grown fleet needs the file
    regenerated and the router restarted (deploy/README.md, "Adding a robot")."""
    conf = _or_usage(lambda: router_config(args.robots, station_cn=args.station_cn, operator_cn=args.operator_cn,
                                           listen=args.listen, certs=args.certs, mocap_cn=args.mocap_cn,
                                           teacher_cn=args.teacher_cn, observer_cn=args.observer_cn or None))
    sys.stdout.write(render(conf, args.command_line))
    return 0


def arguments_client(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--name", required=True, help="the client's certificate CN (a robot's name, operator, ...)")
    ap.add_argument("--connect", default=LAB_LISTEN, help=f"the router's endpoint (default {LAB_LISTEN})")
    ap.add_argument("--certs", default=LAB_CERTS, help=f"directory of ca.crt and <name>.key/.crt "
                                                      f"(default {LAB_CERTS})")


def run_client(args: argparse.Namespace) -> int:
    """Print a client's Zenoh config (JSON5): mutual TLS to the base station's router with this name's
    certificate (a robot's driver host, the operator's console, a station-side tool)."""
    conf = _or_usage(lambda: client_config(args.name, connect=args.connect, certs=args.certs))
    sys.stdout.write(render(conf, args.command_line, CLIENT_HEADER))
    return 0


def arguments_certs(ap: argparse.ArgumentParser) -> None:
    who = ap.add_mutually_exclusive_group(required=True)
    who.add_argument("--robots", type=robots_arg, help="comma-separated robot names (with the station's, the "
                                                       "operator's and the observer's certificates)")
    who.add_argument("--add-robot", type=robots_arg, help="certificates for these robots only, from the CA in --out")
    ap.add_argument("--station-cn", default="station")
    ap.add_argument("--operator-cn", default="operator")
    ap.add_argument("--extra", default="", help="more comma-separated names to certify")
    ap.add_argument("--station-address", action="append", default=[],
                    help="an address clients use to reach the router, written into the station's certificate "
                         "(repeatable; default 127.0.0.1)")
    ap.add_argument("--days", type=int, default=365, help="validity of each certificate, days (default 365; printed)")
    ap.add_argument("--observer-cn", default="observer", help="the observer's certificate CN (empty: none)")
    ap.add_argument("--out", required=True, help="output directory")


def run_certs(args: argparse.Namespace) -> int:
    """Make a throwaway CA and one certificate per name with openssl, for tests and a lab's first try (a lab
    issues its certificates from its own PKI)."""
    out = Path(args.out)
    if args.add_robot:
        if not (out / "ca.crt").exists():
            raise UsageError(f"--add-robot needs the lab's CA in {out} (ca.crt, ca.key): the one the robots trust")
        for r in args.add_robot:
            M.check_robot(r)
        names = list(args.add_robot)
    else:
        _or_usage(lambda: _check_names(args.robots, args.station_cn, args.operator_cn,
                                       *([args.observer_cn] if args.observer_cn else [])))
        names = [args.station_cn, args.operator_cn, *([args.observer_cn] if args.observer_cn else []),
                 *args.robots, *_names(args.extra)]
    for line in _or_usage(lambda: make_certs(out, names, station_cn=args.station_cn,
                                             station_sans=_sans(args.station_address or ["127.0.0.1"]),
                                             days=args.days)):
        print(line)
    print("a throwaway CA: for tests and a first try; a lab issues its certificates from its own PKI "
          "(deploy/README.md); scmbridge doctor warns before they expire", file=sys.stderr)
    return 0


def _or_usage(fn: Any) -> Any:
    """``fn()``, with its ValueError or RuntimeError (a bad name, openssl missing) as a one-line UsageError."""
    try:
        return fn()
    except (ValueError, RuntimeError) as exc:
        raise UsageError(str(exc)) from None


def arguments_lab(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--robots", type=robots_arg, required=True, help="comma-separated robot names")
    ap.add_argument("--local", action="store_true",
                    help="a lab that runs on this machine as written: the router on 127.0.0.1 at a free port, the "
                         "configs pointing at the certificates where they are made (OUT/tls), a state directory "
                         "per host under OUT/state (deploy/README.md, \"The whole lab on one machine\")")
    ap.add_argument("--station-address", action="append", default=None,
                    help="the address robots and tools reach the router at (repeatable; the first is where it "
                         "listens; needed unless --local)")
    ap.add_argument("--port", type=int, default=None, help="the router's TLS port (default 7447; with --local a "
                                                           "free one)")
    ap.add_argument("--certs", default=None,
                    help=f"where the certificates will be installed on each host (default {LAB_CERTS}; with --local "
                         "OUT/tls, where they are made)")
    ap.add_argument("--days", type=int, default=365, help="validity of each certificate, days (default 365)")
    ap.add_argument("--out", required=True, help="output directory (an existing CA in OUT/tls is kept)")


def local_commands(out: Path, robots: Sequence[str]) -> list[str]:
    """The commands that run the lab ``deploy lab --local`` wrote in ``out``, one per process, each host with its
    own state directory (two driver hosts, or a host and the station, must never share an estop latch file)."""
    o = str(out).rstrip("/")
    cmds = [f"scmbridge router --zenoh-config {o}/router.json5",
            f"SCMBRIDGE_STATE_DIR={o}/state/station scmbridge station --robots {','.join(robots)} "
            f"--zenoh-config {o}/station-client.json5"]
    cmds += [f"SCMBRIDGE_STATE_DIR={o}/state/{r} scmbridge driver --robot {r} --link can --emulate "
             f"--zenoh-config {o}/{r}.json5" for r in robots]
    return cmds


def run_lab(args: argparse.Namespace) -> int:
    """Make a whole secure lab in one command: a CA and the certificates (station, operator, observer, each robot),
    the router's TLS + access-control config (router.json5, for scmbridge-router.service), and every client's
    config (each robot, the operator, the observer, the station: station-client.json5), ready to install.
    Re-running it for a grown fleet keeps the CA and the certificates already made."""
    out, tls = Path(args.out), Path(args.out) / "tls"
    _or_usage(lambda: _check_names(args.robots, "station", "operator", "observer"))
    if args.local:
        from bridge.nodes.zsession import free_port

        addresses = args.station_address or ["127.0.0.1"]
        port = args.port or free_port(addresses[0])
        certs = args.certs or str(tls.resolve())
        for sub in ("state", *(f"state/{n}" for n in ("station", *args.robots))):
            (out / sub).mkdir(mode=0o700, parents=True, exist_ok=True)
    elif not args.station_address:
        raise UsageError("name the address robots and tools reach the router at (--station-address ADDR), or "
                         "--local for a lab on this machine")
    else:
        addresses, port, certs = args.station_address, args.port or 7447, args.certs or LAB_CERTS
    listen = f"tls/{addresses[0]}:{port}"
    for line in _or_usage(lambda: make_certs(tls, ["station", "operator", "observer", *args.robots],
                                             station_sans=_sans(addresses), days=args.days)):
        print(line)
    router = _or_usage(lambda: router_config(args.robots, listen=listen, certs=certs))
    (out / "router.json5").write_text(render(router, args.command_line))
    for name in (*args.robots, "operator", "observer", "station"):
        conf = client_config(name, connect=listen, certs=certs)
        target = {"station": "station-client.json5"}.get(name, f"{name}.json5")
        (out / target).write_text(render(conf, args.command_line, CLIENT_HEADER))
    print(f"wrote {out}/router.json5 (the router: /etc/scmbridge/router.json5, scmbridge-router.service), "
          f"station-client.json5 (the station: /etc/scmbridge/station-client.json5), "
          f"{', '.join(f'{r}.json5' for r in args.robots)} (each robot: /etc/scmbridge/robot-client.json5), "
          f"operator.json5, observer.json5; certificates in {tls} (install ca.crt and each host's own key and "
          f"certificate in {certs}; keep ca.key off the base station)")
    if args.local:
        print(f"a lab on this machine, the router at {listen}; each in its own terminal:")
        for cmd in local_commands(out, args.robots):
            print(f"  {cmd}")
        print(f"then the operator's tools with --zenoh-config {out}/operator.json5 (engage, mission start, status, "
              f"estop) and the observer's with --zenoh-config {out}/observer.json5 (deploy/README.md)")
    return 0
