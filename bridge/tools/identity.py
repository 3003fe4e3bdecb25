"""Denied or nobody there? What the lab's access control lets this tool's identity do.

A router drops what its access control denies without a word to the client: an observer's ``engage`` and a robot's
certificate asking ``mission start`` see exactly what they would see with nobody answering. A tool that knows its
own identity (the CN of the certificate its Zenoh configuration presents, :mod:`bridge.nodes.tlsid`) and the rules
``scmbridge deploy`` generates (:func:`bridge.tools.deploy.access_control`, with its default names: ``station``,
``operator``, ``observer`` and the robots) can tell them apart: when nothing answered and the role of that CN has
no rule letting it send the message, it says "denied" and which role has the right, and exits with
:data:`DENIED_EXIT`; knowing it before it asks, it waits only :data:`DENIED_WAIT_S` for an answer
(:func:`expected_denial`). It never claims a denial it cannot see: without TLS, with a CN the default rules do not name
(a lab's own ``--operator-cn``), or when the role has the right, the tool says "nobody answered" as before.
"""

from __future__ import annotations

import zenoh

from bridge.core import wire as M
from bridge.nodes.tlsid import identity
from bridge.tools import deploy

#: a tool's exit status when the lab's access control denies what it asked (docs/CLI.md: each tool's exit status)
DENIED_EXIT = 3
#: s a tool waits for an answer when its own identity says the router denies what it asks: an answer that comes
#: anyway (a lab whose router runs other rules than the generated ones) is taken; none, and the denial is named
DENIED_WAIT_S = 1.5
#: the roles of the default common names (``scmbridge deploy lab``/``acl`` without ``--*-cn``)
DEFAULT_ROLES = {"station": "station", "operator": "operator", "observer": "observer"}


def _rules(robot: str) -> dict[str, object]:
    return deploy.access_control([robot])


def _allowing(acl: dict, subject: str, message: str, key: str) -> list[str]:
    """The ids of ``subject``'s ingress rules that allow ``message`` on ``key``."""
    rules = {r["id"]: r for r in acl["rules"]}
    ids = [rid for p in acl["policies"] if subject in p["subjects"] for rid in p["rules"]]
    target = zenoh.KeyExpr(key)
    return [rid for rid in ids if "ingress" in rules[rid]["flows"] and message in rules[rid]["messages"]
            and any(zenoh.KeyExpr(k).includes(target) for k in rules[rid]["key_exprs"])]


def role_of(cn: str, robot: str) -> str | None:
    """The subject the default rules give the certificate name ``cn`` (for a robot: ``robot/<name>``), or None."""
    if cn in DEFAULT_ROLES:
        return DEFAULT_ROLES[cn]
    return f"robot/{cn}" if cn == robot else None


def denial(conf: zenoh.Config, robot: str, message: str, key: str, what: str) -> str | None:
    """"denied: ..." when this configuration's identity may not send ``message`` (``put``, ``query``) on ``key``
    under the lab's generated rules, else None (it may, or it cannot be told). ``what``: the action in words."""
    me = identity(conf)
    if me is None:
        return None
    try:
        M.check_robot(robot)
        acl = _rules(robot) if me.cn == robot or me.cn in DEFAULT_ROLES else None
    except ValueError:
        return None
    subject = role_of(me.cn, robot)
    if acl is None or subject is None or _allowing(acl, subject, message, key):
        return None
    who = sorted({f"{s} ({rid})" for s in {x["id"] for x in acl["subjects"]}
                  for rid in _allowing(acl, s, message, key)})
    return (f"denied: identity {me.cn!r} (role {subject}) may not {what}: no rule of its role lets it {message} "
            f"{key} (the lab's rules, scmbridge deploy acl; allowed to "
            f"{', '.join(who) if who else 'no role'}): the router drops it without an answer")


def expected_denial(conf: zenoh.Config, robot: str, message: str, key: str, what: str,
                    timeout: float) -> tuple[str | None, float]:
    """Before asking: the denial this identity expects (:func:`denial`) and how long to wait for an answer:
    ``timeout``, or at most :data:`DENIED_WAIT_S` when a denial is expected, so that it is named at once instead of
    after the whole wait for a robot (an observer's engage waited 40 s for nothing)."""
    denied = denial(conf, robot, message, key, what)
    return denied, (min(timeout, DENIED_WAIT_S) if denied else timeout)


def unnamed_hint(conf: zenoh.Config, robot: str) -> str:
    """A clause for a "nobody answered" error when this identity is none the default rules name ("" otherwise):
    if the router's rules do not name it either, everything it sends is dropped."""
    me = identity(conf)
    if me is None or role_of(me.cn, robot) is not None:
        return ""
    return (f"; this identity, CN {me.cn!r}, is not one the lab's default rules name (station, operator, observer, "
            "the robots): if the router's rules do not name it either, everything it sends is dropped")
