"""The generated lab router config enforces who may say what, checked with real Zenoh sessions over mutual TLS.

One router on a free 127.0.0.1 port runs the config ``scmbridge deploy acl`` writes (only the listen endpoint and the
certificate directory differ from the shipped file), with throwaway certificates from ``scmbridge deploy certs``.
The fleet in the ACL is ``rover1`` and ``rover3``; ``rover2`` has a certificate of the same CA but is not named.

As deployed, the router is a process of its own (``scmbridge router --zenoh-config router.json5``) and the station its
client with the station's certificate: the ``station`` session here. The router's own session (``router``) also
listens and publishes in some tests, as a process inside the router would (the old layout, where the station was
the router): what it publishes is still filtered on the way out to each client. Clients that must be stopped by the
router (forgers) use ``session.put``, which a Zenoh 1.x client sends to the router unconditionally; well-behaved
nodes use declared publishers like ``bridge.nodes.station`` and ``bridge.nodes.driver_host`` do (a declared
publisher sends
only once the router has told it of a matching subscriber, which the ACL must therefore allow too).

Timing: a message that must arrive is waited for, up to ``ARRIVE_S`` (10 s); a message that must not arrive is
sent every 50 ms for ``QUIET_S`` (1 s) while a control message on the same path proves the path was open.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, tcp
from bridge.tools import cli, deploy

ARRIVE_S = 10.0  # a message that should arrive is waited for this long at most (it costs nothing when it comes)
QUIET_S = 1.0  # a message that must not arrive: keep sending it this long, then look
EVERY_S = 0.05
CONNECT_TIMEOUT_MS = 1000  # a refused client gives up after this

FLEET = ("rover1", "rover3")  # named in the ACL
UNNAMED = "rover2"  # a certificate of the lab's CA that the ACL does not name
K1, K2, K3 = M.Keys("rover1"), M.Keys("rover2"), M.Keys("rover3")
EVERYTHING_KEY = f"{M.PREFIX}/**"


# ---------------------------------------------------------------------------------------------------- helpers
class Inbox:
    """What subscribers (or a queryable) received, as (key, payload), safe to read from the test thread."""

    def __init__(self) -> None:
        self._got: list[tuple[str, bytes]] = []
        self._cv = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cv:
            self._got.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cv.notify_all()

    def add(self, key: str, payload: bytes) -> None:
        with self._cv:
            self._got.append((key, payload))
            self._cv.notify_all()

    @property
    def got(self) -> list[tuple[str, bytes]]:
        with self._cv:
            return list(self._got)

    def has(self, payload: bytes, key: str | None = None) -> bool:
        return any(p == payload and (key is None or k == key) for k, p in self.got)

    def wait_for(self, payload: bytes, key: str | None = None, timeout: float = ARRIVE_S) -> bool:
        deadline = time.monotonic() + timeout
        with self._cv:
            while not any(p == payload and (key is None or k == key) for k, p in self._got):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
            return True


@contextlib.contextmanager
def subscribed(session: zenoh.Session, *keys: str) -> Iterator[Inbox]:
    """Callback subscribers on ``keys`` feeding one inbox; undeclared on exit (a declared callback subscriber
    left behind would keep its session from closing)."""
    inbox = Inbox()
    subs = [session.declare_subscriber(k, inbox) for k in keys]
    try:
        yield inbox
    finally:
        for s in subs:
            s.undeclare()


@contextlib.contextmanager
def publishers(session: zenoh.Session, *keys: str) -> Iterator[list[zenoh.Publisher]]:
    """Declared publishers, as the station and the driver host use them."""
    pubs = [session.declare_publisher(k) for k in keys]
    try:
        yield pubs
    finally:
        for p in pubs:
            p.undeclare()


def keep_sending(sends: Sequence[Callable[[], None]], seconds: float = QUIET_S) -> None:
    """Call every ``send`` each ``EVERY_S`` for ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for send in sends:
            send()
        time.sleep(EVERY_S)  # pacing the sends of an absence window (what must not arrive is watched over time)


def send_until(send: Callable[[], None], arrived: Callable[[], bool], timeout: float = ARRIVE_S) -> bool:
    """Send every ``EVERY_S`` until ``arrived()`` (a declared publisher learns of its subscribers a moment after
    they are declared, so the first sends may legitimately go nowhere)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        send()
        if arrived():
            return True
        time.sleep(EVERY_S)  # the poll step of this deadline loop (it also paces the sends)
    return arrived()


def replies(session: zenoh.Session, key: str, timeout: float = QUIET_S) -> list[bytes]:
    """Payloads of every reply to a ``get`` on ``key`` (all queryables, no consolidation)."""
    got = session.get(key, timeout=timeout, target=zenoh.QueryTarget.ALL,
                      consolidation=zenoh.ConsolidationMode.NONE)
    return [r.ok.payload.to_bytes() for r in got if r.ok is not None]


def tag(text: str) -> bytes:
    """A payload no other test sends (the ACL never looks at payloads; tags tell senders apart)."""
    return f"{text}/{time.monotonic_ns()}".encode()


# ---------------------------------------------------------------------------------------------------- the lab
@dataclass
class Lab:
    """A router running the generated config, and one session per identity."""

    certs: Path
    other_ca: Path
    port: int
    router_conf: dict[str, Any]
    router: zenoh.Session  # the router's own session (a process inside the router)
    station: zenoh.Session  # a client with the station's certificate
    rover1: zenoh.Session  # rover1's driver host
    forger: zenoh.Session  # a second session holding rover1's credentials, trying what rover1 must not do
    rover3: zenoh.Session
    rover2: zenoh.Session  # a lab certificate the ACL does not name
    operator: zenoh.Session
    observer: zenoh.Session  # reads everything, changes nothing

    @property
    def endpoint(self) -> str:
        return f"tls/127.0.0.1:{self.port}"

    def client(self, name: str | None, certs: Path | None = None) -> zenoh.Config:
        return client_config(self.endpoint, self.certs, name, certs)


def client_config(endpoint: str, lab_certs: Path, name: str | None, certs: Path | None = None) -> zenoh.Config:
    """A client config as ``scmbridge deploy client`` writes it, with a short connect timeout. ``name=None``
    presents no certificate; ``certs`` takes the client's key and certificate from another directory (the CA it
    trusts for the router stays the lab's)."""
    conf = deploy.client_config(name or "nobody", connect=endpoint, certs=lab_certs)
    tls = conf["transport"]["link"]["tls"]
    if name is None:
        for k in ("connect_private_key", "connect_certificate", "enable_mtls"):
            del tls[k]
    elif certs is not None:
        tls["connect_private_key"] = str(certs / f"{name}.key")
        tls["connect_certificate"] = str(certs / f"{name}.crt")
    conf["connect"].update(timeout_ms=CONNECT_TIMEOUT_MS, exit_on_failure=True)
    return zenoh.Config.from_json5(json.dumps(conf))


def _cli(argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main(["deploy", *argv]) == 0
    return out.getvalue()


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: the throwaway CA and certificates are made with it")
    d = tmp_path_factory.mktemp("acl")
    certs, other = d / "tls", d / "other-ca"
    _cli(["certs", "--robots", ",".join(FLEET), "--extra", UNNAMED, "--station-address", "127.0.0.1",
          "--days", "1", "--out", str(certs)])
    deploy.make_certs(other, ["rover1"], days=1)  # another CA; the certificate even carries a fleet name
    port = free_port()
    text = _cli(["acl", "--robots", ",".join(FLEET), "--listen", f"tls/127.0.0.1:{port}", "--certs", str(certs)])
    path = d / "router-tls-acl.json5"
    path.write_text(text)
    clients = {"station": "station", "rover1": "rover1", "forger": "rover1", "rover3": "rover3", "rover2": UNNAMED,
               "operator": "operator", "observer": "observer"}
    with contextlib.ExitStack() as stack:
        router = stack.enter_context(zenoh.open(make_config(mode="router", config_file=path)))
        conf = json.loads(str(zenoh.Config.from_file(str(path))))
        ep = f"tls/127.0.0.1:{port}"
        sessions = {attr: stack.enter_context(zenoh.open(client_config(ep, certs, cn))) for attr, cn in clients.items()}
        yield Lab(certs, other, port, conf, router, **sessions)


def _refused(conf: zenoh.Config) -> str | None:
    """``None`` if a session opened with ``conf`` (and was closed again), else Zenoh's error."""
    try:
        with zenoh.open(conf):
            return None
    except zenoh.ZError as exc:
        return str(exc)


# -------------------------------------------------------------------------------------- the generated rules
def test_the_generated_rules_give_each_identity_only_its_own_keys() -> None:
    acl = deploy.access_control(["rover1", "rover3"])
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert all(r["permission"] == "allow" and len(r["flows"]) == 1 for r in rules.values())
    # exact keys, but for what the operator's and observer's tools ask and listen on (estop --all, status --all,
    # view --all, record) and a robot's share of those wildcard queries; only the operator publishes on a wildcard,
    # and only the estop (``estop --all`` stops every robot with one put first)
    wild = {k for r in rules.values() for k in r["key_exprs"] if any(c in k for c in "*$?#")}
    assert wild == {deploy.ALL_ESTOPS, deploy.EVERYTHING, deploy.ALL_ALIVE, deploy.ALL_STATUS, "scm/rover1/status/*",
                    "scm/rover3/status/*"}  # (status asks every node for its last status)
    assert [r["id"] for r in rules.values() if "put" in r["messages"] and r["flows"] == ["ingress"]
            and set(r["key_exprs"]) & {deploy.EVERYTHING, deploy.ALL_ESTOPS}] == ["operator/estop"]
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects == {"robot/rover1": ["rover1"], "robot/rover3": ["rover3"], "station": ["station"],
                        "operator": ["operator"], "observer": ["observer"]}

    def allowed(subject: str, flow: str, message: str) -> set[str]:
        ids = [rid for p in acl["policies"] if subject in p["subjects"] for rid in p["rules"]]
        return {k for rid in ids for k in rules[rid]["key_exprs"]
                if flow in rules[rid]["flows"] and message in rules[rid]["messages"]}

    assert allowed("robot/rover1", "ingress", "put") == {K1.state, K1.applied, M.status_key("rover1", "driver")}
    assert allowed("robot/rover1", "egress", "put") == {K1.cmd, K1.estop, deploy.ALL_ESTOPS}  # (estop --all's)
    assert allowed("robot/rover1", "ingress", "declare_subscriber") == {K1.cmd, K1.estop}
    assert allowed("robot/rover1", "ingress", "reply") == {K1.estop, K1.engage, M.status_key("rover1", "driver")}
    # a new mission for a running station is a person's act: the operator's, never the station's certificate
    assert allowed("operator", "ingress", "put") == {K1.estop, K3.estop, deploy.ALL_ESTOPS, K1.mission, K3.mission}
    station_puts = allowed("station", "ingress", "put")
    assert {K1.cmd, K3.cmd, K1.teacher, K1.limits} <= station_puts
    assert not station_puts & {K1.state, K1.applied, K1.estop, K1.mission, K3.mission,
                               M.status_key("rover1", "driver")}
    assert {K1.mission, K3.mission} <= allowed("station", "egress", "put")  # it receives them
    assert allowed("station", "ingress", "reply") == {K1.pairs, K3.pairs, K1.control, K3.control,
                                                     *(M.status_key(r, "station") for r in ("rover1", "rover3"))}
    assert allowed("observer", "ingress", "put") == set() and allowed("observer", "ingress", "query") == {
        K1.pairs, K3.pairs, K1.estop, K3.estop, deploy.ALL_ESTOPS, deploy.ALL_STATUS}  # never control or engage
    # only the station publishes cmd
    others = ("robot/rover1", "robot/rover3", "operator")
    assert [s for s in others if {K1.cmd, K3.cmd} & allowed(s, "ingress", "put")] == []


def test_the_generator_refuses_what_would_open_the_router() -> None:
    with pytest.raises(ValueError, match="TLS only"):
        deploy.router_config(["rover1"], listen="tcp/192.168.50.10:7447")
    with pytest.raises(ValueError, match="every interface"):
        deploy.router_config(["rover1"], listen="tls/0.0.0.0:7447")
    with pytest.raises(ValueError, match="own common name"):
        deploy.access_control(["rover1", "station"])
    with pytest.raises(ValueError, match="robot name"):
        deploy.access_control(["rover/1"])
    assert cli.main(["deploy", "acl", "--robots", "rover1", "--listen", "tls/[::]:7447"]) == 2


# ----------------------------------------------------------------------------------------- who gets in
def test_the_router_listens_on_tls_only(lab: Lab) -> None:
    assert lab.router_conf["listen"]["endpoints"] == [lab.endpoint]
    assert lab.router_conf["transport"]["link"]["protocols"] == ["tls"]
    assert lab.router_conf["transport"]["link"]["tls"]["enable_mtls"] is True
    # every client the fixture opened is there, under its certificate's name
    names = Counter(link.auth_identifier for link in lab.router.info.links())
    assert Counter(["station", "rover1", "rover1", "rover3", UNNAMED, "operator"]) <= names


@pytest.mark.parametrize("who", ["no certificate", "another CA's certificate", "plain TCP"])
def test_a_client_the_router_cannot_authenticate_is_refused(lab: Lab, who: str) -> None:
    if who == "no certificate":
        conf = lab.client(None)
    elif who == "another CA's certificate":
        conf = lab.client("rover1", certs=lab.other_ca)  # a fleet name, signed by a CA the router does not trust
    else:  # the shipped plain robot-client.json5, pointed at the router's port
        conf = make_config(mode="client", connect=[tcp(lab.port)])
        conf.insert_json5("connect/timeout_ms", str(CONNECT_TIMEOUT_MS))
        conf.insert_json5("connect/exit_on_failure", "true")
    before = {str(link.zid) for link in lab.router.info.links()}
    assert _refused(conf) is not None, f"a client with {who} connected"
    assert {str(link.zid) for link in lab.router.info.links()} <= before  # and the router holds no link for it
    assert _refused(lab.client("operator")) is None  # control: the same client with a lab certificate connects


# ---------------------------------------------------------------------------------------- what gets through
def test_rover1_cannot_publish_cmd_not_even_its_own(lab: Lab) -> None:
    forged, legit = tag("forged-cmd"), tag("station-cmd")
    with subscribed(lab.router, K1.cmd) as station_sees, subscribed(lab.rover1, K1.cmd) as driver_sees, \
            publishers(lab.station, K1.cmd) as (cmd,):
        assert send_until(lambda: cmd.put(legit), lambda: driver_sees.has(legit))  # control: the path is open
        keep_sending([lambda: lab.forger.put(K1.cmd, forged), lambda: cmd.put(legit)])
        assert station_sees.wait_for(legit)
    assert not station_sees.has(forged), "the station's subscriber got a cmd published with rover1's credentials"
    assert not driver_sees.has(forged), "rover1's driver host got a cmd published with rover1's credentials"


def test_rover1_cannot_publish_another_robots_state(lab: Lab) -> None:
    forged, legit = tag("forged-state"), tag("rover3-state")
    with subscribed(lab.router, K2.state, K3.state) as station_sees, subscribed(lab.station, K3.state) as client_sees, \
            publishers(lab.rover3, K3.state) as (state3,):
        assert send_until(lambda: state3.put(legit), lambda: client_sees.has(legit))  # control
        keep_sending([lambda: lab.forger.put(K2.state, forged), lambda: lab.forger.put(K3.state, forged)])
        assert station_sees.wait_for(legit)
    assert not station_sees.has(forged), f"rover1 published another robot's state: {station_sees.got}"
    assert not client_sees.has(forged)


def test_rover1_cannot_publish_estop_not_even_to_release_its_own(lab: Lab) -> None:
    release = M.encode(M.Estop(stamp=1.0, engaged=False, source="rover1"))
    engage = M.encode(M.Estop(stamp=1.5, engaged=True, source="operator"))
    with subscribed(lab.rover1, K1.estop) as driver_sees, subscribed(lab.router, K1.estop) as station_sees, \
            publishers(lab.operator, K1.estop) as (estop,):
        assert send_until(lambda: estop.put(engage), lambda: driver_sees.has(engage))  # control: the path is open
        keep_sending([lambda: lab.forger.put(K1.estop, release)])
        assert station_sees.wait_for(engage)
    assert not driver_sees.has(release) and not station_sees.has(release), "rover1 released its own estop"


def test_only_the_operator_publishes_a_mission_and_the_station_receives_it(lab: Lab) -> None:
    """Finding (issue 31): under `deploy lab` the station's certificate could replace a robot's mission, and the
    operator then started it unwarned. Only the operator's identity may put on scm/<robot>/mission."""
    legit, forged = tag("operator-mission"), tag("station-mission")
    with subscribed(lab.station, K1.mission) as station_sees, subscribed(lab.router, K1.mission) as router_sees, \
            publishers(lab.operator, K1.mission) as (mission,):
        assert send_until(lambda: mission.put(legit), lambda: station_sees.has(legit))  # control: the path is open
        keep_sending([lambda: lab.station.put(K1.mission, forged), lambda: lab.rover1.put(K1.mission, forged),
                      lambda: lab.observer.put(K1.mission, forged)])
        assert router_sees.wait_for(legit)
    assert not router_sees.has(forged), "a certificate other than the operator's published a mission"


def test_rover1_publishes_its_telemetry_and_the_station_receives_it(lab: Lab) -> None:
    keys = (K1.state, K1.applied, M.status_key("rover1", "driver"))
    msgs = {k: tag(k) for k in keys}
    with subscribed(lab.router, *keys) as station_sees, subscribed(lab.station, *keys) as client_sees, \
            publishers(lab.rover1, *keys) as pubs:
        for key, pub in zip(keys, pubs):
            ok = send_until(lambda p=pub, k=key: p.put(msgs[k]),
                            lambda k=key: station_sees.has(msgs[k], k) and client_sees.has(msgs[k], k))
            assert ok, f"{key} from rover1 did not reach the station within {ARRIVE_S} s"


def test_the_station_cmd_reaches_rover1_but_rover1_gets_no_other_robots_cmd(lab: Lab) -> None:
    mine, from_router, theirs = tag("cmd-rover1"), tag("cmd-rover1-in-router"), tag("cmd-other")
    with subscribed(lab.rover1, K1.cmd, K2.cmd, K3.cmd, "scm/**") as rover1_sees, \
            subscribed(lab.rover3, K3.cmd) as rover3_sees, publishers(lab.station, K1.cmd, K3.cmd) as (cmd1, cmd3), \
            publishers(lab.router, K1.cmd) as (in_router,):
        assert send_until(lambda: cmd1.put(mine), lambda: rover1_sees.has(mine, K1.cmd)), "station cmd lost"
        assert send_until(lambda: in_router.put(from_router), lambda: rover1_sees.has(from_router, K1.cmd))
        assert send_until(lambda: cmd3.put(theirs), lambda: rover3_sees.has(theirs, K3.cmd))  # control
        keep_sending([lambda: cmd3.put(theirs), lambda: lab.router.put(K2.cmd, theirs),
                      lambda: lab.router.put(K3.cmd, theirs)])
    others = [(k, p) for k, p in rover1_sees.got if not k.startswith("scm/rover1/")]
    assert others == [], f"rover1 received other robots' messages: {others[:3]}"


def test_the_operator_estop_reaches_rover1_and_rover1_answers_estop_queries(lab: Lab) -> None:
    engage = M.encode(M.Estop(stamp=2.0, seq=1, engaged=True, source="operator", reason="test"))
    release = M.encode(M.Estop(stamp=3.0, seq=2, engaged=False, source="operator"))
    state = M.encode(M.EstopState(stamp=1.0, node="driver", latched=True, source="operator"))

    def answer(query: zenoh.Query) -> None:
        query.reply(K1.estop, state)

    with subscribed(lab.rover1, K1.estop) as driver_sees, publishers(lab.operator, K1.estop) as (estop,):
        assert send_until(lambda: estop.put(engage), lambda: driver_sees.has(engage)), "estop engage lost"
        assert send_until(lambda: estop.put(release), lambda: driver_sees.has(release)), "estop release lost"
        q = lab.rover1.declare_queryable(K1.estop, answer)
        try:
            assert send_until(lambda: None, lambda: state in replies(lab.operator, K1.estop, timeout=0.5))
            assert replies(lab.rover3, K1.estop) == []  # another robot cannot ask
        finally:
            q.undeclare()
    assert M.decode(driver_sees.got[-1][1], M.Estop).source == "operator"


def test_the_operators_wildcard_estop_reaches_every_robot_and_no_one_else_may_put_it(lab: Lab) -> None:
    """Found: under the lab's rules ``estop --all``'s first stop, one put on ``scm/*/estop``, was dropped by the
    router (only the per-robot puts after it arrived). The operator's wildcard estop reaches each robot's driver
    host on its own key; a robot, the station and the observer putting the same are dropped."""
    stop = M.encode(M.Estop(stamp=5.0, seq=1, engaged=True, source="operator", reason="all"))
    with subscribed(lab.rover1, K1.estop) as rover1_sees, subscribed(lab.rover3, K3.estop) as rover3_sees, \
            publishers(lab.operator, deploy.ALL_ESTOPS) as (estop,):
        assert send_until(lambda: estop.put(stop), lambda: rover1_sees.has(stop) and rover3_sees.has(stop)), \
            "the operator's wildcard estop was dropped"
    for who in (lab.rover3, lab.station, lab.observer):
        forged = M.encode(M.Estop(stamp=6.0, seq=1, engaged=False, source="operator", reason=str(id(who))))
        with subscribed(lab.rover1, K1.estop) as rover1_sees:
            keep_sending([lambda who=who, forged=forged: who.put(deploy.ALL_ESTOPS, forged)])
            assert not rover1_sees.has(forged)


def test_pairs_are_answered_by_the_station_only(lab: Lab) -> None:
    real, fake = tag("pairs-station"), tag("pairs-rover1")
    queried = Inbox()

    def station_answers(query: zenoh.Query) -> None:
        query.reply(K1.pairs, real)

    def impostor(query: zenoh.Query) -> None:
        queried.add(str(query.key_expr), b"")
        query.reply(K1.pairs, fake)

    qs = [lab.station.declare_queryable(K1.pairs, station_answers), lab.forger.declare_queryable(K1.pairs, impostor)]
    try:
        assert send_until(lambda: None, lambda: real in replies(lab.operator, K1.pairs, timeout=0.5))
        assert fake not in replies(lab.operator, K1.pairs)
        assert replies(lab.rover1, K1.pairs) == []  # a robot does not read the store
        assert queried.got == []
    finally:
        for q in qs:
            q.undeclare()


# ------------------------------------------------------------------------------ a certificate the ACL does not name
def test_an_unnamed_certificate_connects_but_receives_nothing(lab: Lab) -> None:
    assert UNNAMED in [link.auth_identifier for link in lab.router.info.links()]  # it is connected
    cmd, state, estop = tag("cmd"), tag("state"), M.encode(M.Estop(stamp=4.0, source="operator"))
    queried = Inbox()
    q = lab.rover2.declare_queryable(K1.estop, lambda query: queried.add(str(query.key_expr), b""))
    try:
        with subscribed(lab.rover2, "scm/**", K1.cmd, K1.state, K2.cmd, K1.estop) as rover2_sees, \
                subscribed(lab.rover1, K1.cmd, K1.estop) as rover1_sees, \
                subscribed(lab.station, K1.state) as station_sees, \
                publishers(lab.station, K1.cmd) as (c,), publishers(lab.rover1, K1.state) as (s,), \
                publishers(lab.operator, K1.estop) as (e,):
            # controls: the same traffic reaches the named identities
            assert send_until(lambda: c.put(cmd), lambda: rover1_sees.has(cmd))
            assert send_until(lambda: s.put(state), lambda: station_sees.has(state))
            assert send_until(lambda: e.put(estop), lambda: rover1_sees.has(estop))
            keep_sending([lambda: c.put(cmd), lambda: s.put(state), lambda: e.put(estop),
                          lambda: lab.router.put(K2.cmd, cmd)])
            replies(lab.operator, K1.estop, timeout=0.2)
        assert rover2_sees.got == [], f"an unnamed certificate received {rover2_sees.got[:3]}"
        assert queried.got == [], "an unnamed certificate was asked an estop query"
    finally:
        q.undeclare()


def test_an_unnamed_certificate_publishes_nothing(lab: Lab) -> None:
    x, state = tag("rover2"), tag("rover1-state")
    release = M.encode(M.Estop(stamp=5.0, engaged=False, source="operator"))
    estop_state = M.encode(M.EstopState(stamp=5.0, node="driver", latched=False))
    keys = (K1.state, K2.state, K1.cmd, K2.cmd)
    qs = [lab.rover1.declare_queryable(K1.estop, lambda q: q.reply(K1.estop, estop_state)),
          lab.station.declare_queryable(K1.pairs, lambda q: q.reply(K1.pairs, x))]
    try:
        with subscribed(lab.router, *keys, K1.estop) as station_sees, \
                subscribed(lab.station, K1.state) as client_sees, \
                subscribed(lab.rover1, K1.cmd, K1.estop) as rover1_sees, publishers(lab.rover1, K1.state) as (s,):
            assert send_until(lambda: s.put(state), lambda: client_sees.has(state))  # control: the path is open
            keep_sending([lambda: [lab.rover2.put(k, x) for k in keys], lambda: lab.rover2.put(K1.estop, release)])
            # the queries an unnamed certificate sends go unanswered, while the operator's are answered
            assert replies(lab.rover2, K1.estop) == [] and replies(lab.rover2, K1.pairs) == []
            assert estop_state in replies(lab.operator, K1.estop) and x in replies(lab.operator, K1.pairs)
        assert not station_sees.has(x) and not station_sees.has(release), station_sees.got[:3]
        assert not client_sees.has(x) and not rover1_sees.got, "a message of an unnamed certificate got through"
    finally:
        for q in qs:
            q.undeclare()


def test_optional_mocap_and_teacher_identities_get_only_their_keys() -> None:
    from bridge.tools.deploy import access_control

    acl = access_control(["rover1", "rover2"], mocap_cn="mocap", teacher_cn="teacher")
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["mocap/publishes"]["key_exprs"] == ["scm/rover1/mocap", "scm/rover2/mocap"]
    assert rules["mocap/publishes"]["messages"] == ["put"] and rules["mocap/publishes"]["flows"] == ["ingress"]
    assert rules["teacher/publishes"]["key_exprs"] == ["scm/rover1/teacher", "scm/rover2/teacher"]
    assert set(rules["teacher/receives"]["key_exprs"]) == {"scm/rover1/state", "scm/rover2/state",
                                                           "scm/rover1/limits", "scm/rover2/limits"}
    assert "scm/rover1/mocap" in rules["robot/rover1/receives"]["key_exprs"]
    assert "scm/rover2/mocap" not in rules["robot/rover1/receives"]["key_exprs"]
    assert not any("cmd" in k for r in acl["rules"] if r["id"].startswith(("mocap", "teacher"))
                   for k in r["key_exprs"])
    without = access_control(["rover1"])
    assert "scm/rover1/mocap" not in {k for r in without["rules"] for k in r["key_exprs"]}


# ------------------------------------------------------------------------- the operator's and observer's tools
def test_the_operators_wildcard_tools_reach_every_robot_through_the_rules(lab: Lab) -> None:
    """Finding: `estop --all` did nothing under the lab's TLS + access control (the wildcard query was denied), and
    `status`, `view`, `record` saw nothing. The operator's wildcard query finds every robot's latch, its status
    subscription hears every robot, it finds the robots' liveliness tokens, and its engage and mission requests
    reach the driver host and the station."""
    latch = M.encode(M.EstopState(stamp=1.0, node="driver", latched=False))
    engaged = M.encode(M.EngageState(stamp=1.0, node="driver", engaged=True))
    mission = M.encode(M.MissionState(stamp=1.0, robot="rover1", phase="running"))
    qs = [lab.rover1.declare_queryable(K1.estop, lambda q: q.reply(K1.estop, latch)),
          lab.rover1.declare_queryable(K1.engage, lambda q: q.reply(K1.engage, engaged)),
          lab.router.declare_queryable(K1.control, lambda q: q.reply(K1.control, mission))]
    token = lab.rover1.liveliness().declare_token(M.alive_key("rover1", "driver"))
    status = M.encode(M.Status(stamp=1.0, seq=1, node="driver", state="driving"))
    try:
        assert send_until(lambda: None, lambda: latch in replies(lab.operator, deploy.ALL_ESTOPS, timeout=0.5))
        assert send_until(lambda: None, lambda: engaged in replies(lab.operator, K1.engage, timeout=0.5))
        assert send_until(lambda: None, lambda: mission in replies(lab.operator, K1.control, timeout=0.5))
        alive = [str(r.ok.key_expr) for r in lab.operator.liveliness().get(deploy.ALL_ALIVE, timeout=1.0)
                 if r.ok is not None]
        assert M.alive_key("rover1", "driver") in alive
        with subscribed(lab.operator, f"{M.PREFIX}/*/status/**") as seen, \
                publishers(lab.rover1, M.status_key("rover1", "driver")) as (pub,):
            assert send_until(lambda: pub.put(status), lambda: seen.has(status))
    finally:
        token.undeclare()
        for q in qs:
            q.undeclare()


def test_the_observer_reads_everything_and_changes_nothing(lab: Lab) -> None:
    state = tag("state-for-observer")
    asked = Inbox()
    qs = [lab.router.declare_queryable(K1.control, lambda q: asked.add(str(q.key_expr), b"control")),
          lab.rover1.declare_queryable(K1.engage, lambda q: asked.add(str(q.key_expr), b"engage"))]
    try:
        with subscribed(lab.observer, EVERYTHING_KEY) as seen, publishers(lab.rover1, K1.state) as (pub,):
            assert send_until(lambda: pub.put(state), lambda: seen.has(state)), "observer saw nothing"
        with subscribed(lab.rover1, K1.estop) as driver_sees:
            forged = M.encode(M.Estop(stamp=1.0, engaged=False, source="operator"))
            keep_sending([lambda: lab.observer.put(K1.estop, forged)])
            assert not driver_sees.has(forged)
        assert replies(lab.observer, K1.control) == [] and replies(lab.observer, K1.engage) == []
        assert asked.got == []  # the requests never reached the station or the driver host
    finally:
        for q in qs:
            q.undeclare()


# ------------------------------------------------------------------------------- the tools say why (issue 32, item 6)
def test_a_certificate_of_another_ca_is_named_as_such_by_the_tools(lab: Lab) -> None:
    """Finding: a certificate of another CA showed as "cannot reach the Zenoh router ... is it up"; and every
    generated CA had the same name, so nothing could have told the two apart."""
    from bridge.core.errors import UsageError
    from bridge.nodes.tlsid import cert_names
    from bridge.nodes.zsession import open_session

    lab_ca, other_ca = cert_names(str(lab.certs / "ca.crt")), cert_names(str(lab.other_ca / "ca.crt"))
    assert lab_ca and other_ca and lab_ca[0] != other_ca[0] and lab_ca[0].startswith("scmbridge lab CA ")
    with pytest.raises(UsageError) as err, open_session(lab.client("rover1", certs=lab.other_ca)):
        pass
    text = str(err.value)
    assert "refuses this certificate" in text and other_ca[0] in text and lab_ca[0] in text, text


def test_the_tools_tell_denied_from_nobody_answered_by_their_identity(lab: Lab) -> None:
    """Finding: an observer's `engage` and `mission send` said "no driver host answered" / "no station answered":
    the router drops a denied query without a word. The tool reads its certificate's CN and the lab's rules."""
    from bridge.tools.identity import denial

    observer, operator, rover1 = lab.client("observer"), lab.client("operator"), lab.client("rover1")
    said = denial(observer, "rover1", "query", K1.engage, "engage a robot")
    assert said and "identity 'observer' (role observer) may not engage a robot" in said, said
    assert "operator (operator/queries)" in said  # who has the right
    assert denial(operator, "rover1", "query", K1.engage, "engage") is None  # it may: nobody answered, then
    assert denial(observer, "rover1", "query", K1.estop, "ask the latch") is None
    assert denial(rover1, "rover1", "query", K1.control, "start a mission") is not None
    assert denial(operator, "rover1", "put", K1.cmd, "calibrate") is not None
    assert denial(lab.client("station"), "rover1", "put", K1.cmd, "calibrate") is None
    # an identity the default rules do not name, or no TLS at all: it cannot be told, nothing is claimed
    assert denial(lab.client(UNNAMED), "rover1", "query", K1.engage, "engage") is None
    assert denial(make_config(mode="client", connect=[tcp(lab.port)]), "rover1", "query", K1.engage, "x") is None
