"""``scmbridge router`` (:mod:`bridge.nodes.router`): its arguments, the endpoints and access control read from a
configuration, the refusals of :func:`router_config` with their lines, and the wait that ends its run. No process is
started here: the router as a process, with a station and a driver host beside it, is in
tests/integration/test_router.py (also its command line refusing no endpoint or a wildcard)."""

from __future__ import annotations

import argparse
import json
import threading
import time

import pytest
import zenoh

from bridge.core.errors import UsageError
from bridge.nodes import router
from bridge.nodes.zsession import make_config


def _args(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    router.arguments(ap)
    return ap.parse_args(list(argv))


def test_the_arguments_repeat_listen_and_connect_and_default_to_running_until_a_signal() -> None:
    a = _args()
    assert (a.zenoh_config, a.listen, a.connect, a.duration) == (None, [], [], None)
    a = _args("--listen", "tcp/127.0.0.1:1", "--listen", "tcp/127.0.0.1:2", "--connect", "tcp/10.0.0.1:7447",
              "--duration", "2.5")
    assert a.listen == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"] and a.connect == ["tcp/10.0.0.1:7447"]
    assert a.duration == 2.5


def test_listening_on_reads_the_endpoints_or_zenohs_per_mode_default() -> None:
    assert router.listening_on(make_config(listen=["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"])) == [
        "tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]
    assert router.listening_on(make_config()) == []
    assert router.listening_on(zenoh.Config()) == ["tcp/[::]:7447"]  # a file naming none: the router's default


def test_the_access_control_in_one_phrase() -> None:
    conf = zenoh.Config()
    assert router.acl_summary(conf) == "no access control"  # Zenoh's default: disabled
    conf.insert_json5("access_control", json.dumps({
        "enabled": True, "default_permission": "deny",
        "rules": [{"id": "r", "messages": ["put"], "flows": ["ingress"], "permission": "allow", "key_exprs": ["a"]}],
        "subjects": [{"id": "s1", "cert_common_names": ["station", "operator"]},
                     {"id": "s2", "cert_common_names": ["rover1", "operator"]}],
        "policies": [{"rules": ["r"], "subjects": ["s1", "s2"]}]}))
    assert router.acl_summary(conf) == ("access control (default deny) naming 3 identities: operator, rover1, "
                                        "station")


def test_router_config_takes_loopback_endpoints_in_router_mode() -> None:
    conf = router.router_config(_args("--listen", "tcp/127.0.0.1:7447"))
    assert json.loads(conf.get_json("mode")) == "router"
    assert router.listening_on(conf) == ["tcp/127.0.0.1:7447"]


@pytest.mark.parametrize(("argv", "says"), [
    ((), "name the endpoint to listen on: --listen tcp/ADDR:PORT"),
    (("--listen", "tcp/0.0.0.0:7447"), "not on every interface (tcp/0.0.0.0:7447)"),
    (("--listen", "tcp/127.0.0.1:7447", "--listen", "tcp/[::]:7448"), "not on every interface (tcp/[::]:7448)"),
])
def test_router_config_refuses_no_endpoint_or_every_interface(argv, says: str) -> None:
    with pytest.raises(UsageError, match=says.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        router.router_config(_args(*argv))


def test_a_file_of_another_mode_or_naming_no_endpoint_is_refused(tmp_path) -> None:
    f = tmp_path / "client.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7447"] } }\n')
    with pytest.raises(UsageError, match=f'{f} is a client\'s file: the router needs mode "router"'):
        router.router_config(_args("--zenoh-config", str(f)))
    g = tmp_path / "router.json5"
    g.write_text('{ mode: "router" }\n')  # Zenoh's default would listen on every interface
    with pytest.raises(UsageError, match="not on every interface"):
        router.router_config(_args("--zenoh-config", str(g)))
    assert router.listening_on(router.router_config(_args("--zenoh-config", str(g), "--listen",
                                                          "tcp/127.0.0.1:7447"))) == ["tcp/127.0.0.1:7447"]


def test_the_wait_ends_at_once_on_a_past_end_or_a_set_stop() -> None:
    stop = threading.Event()
    t0 = time.monotonic()
    router._wait(stop, t0 - 1.0)  # the duration is over
    stop.set()
    router._wait(stop, None)  # a signal came
    assert time.monotonic() - t0 < 0.5


def test_the_wait_ends_when_the_stop_is_set_from_another_thread() -> None:
    stop = threading.Event()
    threading.Timer(0.05, stop.set).start()
    t0 = time.monotonic()
    router._wait(stop, None)  # woken by the event, not by polling a clock
    assert stop.is_set() and time.monotonic() - t0 < 5.0
