"""Denied or nobody there (:mod:`bridge.tools.identity`): the role of a certificate's name under the lab's default
rules, the "denied: ..." line for what a role may not send (naming the roles that may), and the hint for an identity
the default rules do not name. Identities come from throwaway certificates (tests/unit/bridge/conftest.py); nothing
is opened. The same lines against a real TLS router with its access control: tests/integration/test_zenoh_acl.py."""

from __future__ import annotations

import pytest

from bridge.core import wire as M
from bridge.nodes.zsession import make_config
from bridge.tools.identity import DEFAULT_ROLES, DENIED_EXIT, denial, role_of, unnamed_hint

K = M.Keys("rover1")


def test_the_default_names_have_their_roles_and_a_robot_is_its_own() -> None:
    assert {cn: role_of(cn, "rover1") for cn in ("station", "operator", "observer")} == DEFAULT_ROLES
    assert role_of("rover1", "rover1") == "robot/rover1"
    assert role_of("rover2", "rover1") is None  # another robot's certificate, asked about rover1: not told
    assert role_of("visitor", "rover1") is None
    assert DENIED_EXIT == 3


def test_the_observer_may_not_engage_and_is_told_which_roles_may(certs) -> None:
    why = denial(certs.client("observer"), "rover1", "query", K.engage, "engage a robot")
    assert why is not None and why.startswith("denied: identity 'observer' (role observer) may not engage a robot: "
                                              f"no rule of its role lets it query {K.engage}")
    assert "operator (" in why and why.endswith("the router drops it without an answer")
    assert "observer (" not in why


@pytest.mark.parametrize(("cn", "message", "key"), [
    ("operator", "query", K.engage),
    ("station", "put", K.cmd),
    ("observer", "query", K.estop),  # it may ask the latch
    ("rover1", "put", K.state),
])
def test_what_a_role_may_send_is_no_denial(certs, cn: str, message: str, key: str) -> None:
    assert denial(certs.client(cn), "rover1", message, key, "do it") is None


@pytest.mark.parametrize(("cn", "message", "key", "role"), [
    ("rover1", "query", K.control, "robot/rover1"),
    ("operator", "put", K.cmd, "operator"),
    ("observer", "put", K.estop, "observer"),
])
def test_what_a_role_may_not_send_is_denied_naming_the_role(certs, cn: str, message: str, key: str, role: str) -> None:
    why = denial(certs.client(cn), "rover1", message, key, "act")
    assert why is not None and f"identity {cn!r} (role {role}) may not act" in why


def test_no_denial_is_claimed_where_it_cannot_be_told(certs) -> None:
    assert denial(make_config(), "rover1", "query", K.engage, "engage") is None  # no TLS
    assert denial(certs.client("visitor"), "rover1", "query", K.engage, "engage") is None  # a name the rules lack
    assert denial(certs.client("rover1"), "rover2", "query", M.key("rover2", "control"), "start") is None
    assert denial(certs.client("observer"), "bad/name", "query", "scm/x/engage", "engage") is None


def test_the_hint_names_an_identity_the_default_rules_do_not(certs) -> None:
    hint = unnamed_hint(certs.client("visitor"), "rover1")
    assert hint.startswith("; this identity, CN 'visitor', is not one the lab's default rules name")
    assert "everything it sends is dropped" in hint
    assert unnamed_hint(certs.client("operator"), "rover1") == ""
    assert unnamed_hint(certs.client("rover1"), "rover1") == ""
    assert unnamed_hint(make_config(), "rover1") == ""


def test_a_denial_is_expected_before_asking_and_the_wait_is_short(certs) -> None:
    """Finding: the observer's engage was denied after 40.2 s of silence. Known before asking, the tool waits only
    DENIED_WAIT_S for an answer that cannot come; one that may ask waits its whole timeout."""
    from bridge.tools.identity import DENIED_WAIT_S, expected_denial

    why, wait = expected_denial(certs.client("observer"), "rover1", "query", K.engage, "engage a robot", 40.0)
    assert why and wait == DENIED_WAIT_S <= 2.0
    assert expected_denial(certs.client("operator"), "rover1", "query", K.engage, "engage", 40.0) == (None, 40.0)


def test_a_robots_certificate_may_not_read_the_statuses_and_the_observer_may(certs) -> None:
    from bridge.tools.status import _denial

    why = _denial(certs.client("rover1"), None, "scm/*/status/*")
    assert why and why.startswith("denied: identity 'rover1' (role robot/rover1) may not read the robots' status")
    assert _denial(certs.client("observer"), None, "scm/*/status/*") is None
    assert _denial(certs.client("operator"), ["rover1"], "scm/rover1/status/*") is None
