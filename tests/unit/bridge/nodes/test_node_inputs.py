"""A node's queued inputs on a real Zenoh session: what the loop drains, in order, the malformed ones counted, and a
full ring keeping the newest samples without blocking the session."""

from __future__ import annotations

import time

from bridge.core import wire as M
from bridge.nodes.node import Inputs
from bridge.nodes.zsession import free_port, make_config, open_session, tcp


def _state(seq: int) -> bytes:
    return M.encode(M.LearnerState(stamp=float(seq), seq=seq, x=1.0, y=2.0, theta=0.5))


def test_a_queued_input_drains_in_order_counts_the_malformed_and_a_full_ring_keeps_the_newest() -> None:
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as hub, \
            open_session(make_config(mode="client", connect=[tcp(port)])) as node:
        inputs = Inputs()
        q = inputs.queue(node, "scm/q1/state", M.LearnerState, "state", capacity=8)
        small = inputs.queue(node, "scm/q1/small", M.LearnerState, "small", capacity=4)
        pub, pub_small = hub.declare_publisher("scm/q1/state"), hub.declare_publisher("scm/q1/small")

        def drain_until(seq: int, now: float) -> list:
            got: list = []
            deadline = time.monotonic() + 10.0
            while not any(m.seq == seq for m, _ in got) and time.monotonic() < deadline:
                got += q.drain(now)
                time.sleep(0.02)
            return got

        deadline = time.monotonic() + 10.0
        while not q.drain(0.0) and time.monotonic() < deadline:  # the route is up once a probe gets through
            pub.put(_state(0))
            time.sleep(0.05)
        for seq in range(1, 7):
            pub.put(_state(seq))
            pub_small.put(_state(seq))
            if seq == 3:
                pub.put(b"\xff not a message")
        pub.put(_state(7))  # sent after every sample above: once it is in, they all are
        got = drain_until(7, 42.0)
        assert [m.seq for m, _ in got] == [1, 2, 3, 4, 5, 6, 7] and {t for _, t in got} == {42.0}
        assert inputs.snapshot()["malformed_state"] == 1
        # six samples into a ring of four, nobody reading: nothing was held up (the other key's samples all came),
        # and the ring kept the newest
        assert [m.seq for m, _ in small.drain(0.0)] == [3, 4, 5, 6]
