"""A node's queued inputs on a real Zenoh session: what the loop drains, in order, the malformed ones counted, and a
full ring keeping the newest samples without blocking the session; its answered queries: a flood of them holds up no
sample behind it (docs/SECURITY.md, ``acts_flood_one_identity``)."""

from __future__ import annotations

import threading
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


def test_a_flood_of_queries_answered_slower_than_it_comes_holds_up_no_sample_behind_it() -> None:
    """4096 queries on one key, then a sample (a person's estop) from the same session, so behind them on the same
    link. Answered by a plain function (zenoh-python's own thread, fed through a bounded channel), Zenoh's receiving
    thread waited whenever the answers lagged, and the sample with it, for seconds. Answered from a ring
    (:meth:`Inputs.answer`), the sample's callback runs while most of the flood is still unanswered."""
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])), \
            open_session(make_config(mode="client", connect=[tcp(port)])) as node, \
            open_session(make_config(mode="client", connect=[tcp(port)])) as asker:
        inputs = Inputs()
        answered = [0]

        def answer(query) -> None:
            answered[0] += 1
            time.sleep(0.0005)  # stall: an answer slower than the flood comes (the host's decode, lock, act check)
            query.reply("scm/q2/engage", b"refused")

        inputs.answer(node, "scm/q2/engage", "engage", answer)
        seen: list[tuple[float, int, bytes]] = []
        got = threading.Event()

        def on_sample(sample) -> None:  # a plain function, as the driver host's estop subscriber
            seen.append((time.monotonic(), answered[0], sample.payload.to_bytes()))
            got.set()

        inputs.declared.keep(node.declare_subscriber("scm/q2/estop", on_sample))
        deadline = time.monotonic() + 10.0
        while not got.is_set() and time.monotonic() < deadline:  # the route is up once a probe gets through
            asker.put("scm/q2/estop", b"probe")
            got.wait(0.05)  # poll
        replies = list(asker.get("scm/q2/engage", timeout=5.0))
        assert [r.ok.payload.to_bytes() if r.ok else r.err.payload.to_bytes() for r in replies] == [b"refused"]
        seen.clear()
        got.clear()
        answered[0] = 0
        flood = [asker.get("scm/q2/engage", timeout=5.0) for _ in range(4096)]
        t0 = time.monotonic()
        asker.put("scm/q2/estop", b"stop")
        assert got.wait(10.0)
        at, answered_then, payload = next(s for s in seen if s[2] == b"stop")
        for handler in flood:  # every query ends: answered, or dropped from the full ring (ended unanswered)
            for _ in handler:
                pass
        inputs.declared.undeclare()
        assert answered_then < 4096 and at - t0 < 1.0, (answered_then, at - t0)
