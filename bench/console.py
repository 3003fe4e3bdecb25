"""``scmbridge bench console``: how long the operator's ``scmbridge status`` takes when every node answers (JSON).

A Zenoh router on a free 127.0.0.1 port (this process) holds a station's and a driver host's status keys as the
nodes hold them (:class:`bridge.nodes.node.StatusOut`: a publisher, each second, and a queryable answering the last
status), for ``--count`` robots. Each repetition runs ``python -m bridge status --robot R`` (or ``--all``) as the
operator does, a process of its own, and times it from its start to its exit (the interpreter's start and the imports
included); the tool's own phases come from one in-process call: opening the session, and asking until every node
answered. A repetition that exits with another status than 0 is an error. Target: under 0.5 s a call (the
operator's console answers at once; it listened a fixed 1.5 s before).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import threading
import time

import numpy as np

from bench.common import emit
from bridge.core import wire as M
from bridge.nodes.node import StatusOut
from bridge.nodes.zsession import free_port, make_config, open_session, tcp

#: the target for one ``status`` call, s
TARGET_S = 0.5


def _statuses(robot: str) -> dict[str, M.Status]:
    return {"station": M.Status(stamp=0.0, seq=0, node="station", ok=True, state="driving", reason="ok",
                                text="driving", progress=0.3),
            "driver": M.Status(stamp=0.0, seq=0, node="driver", ok=True, state="driving", reason="ok",
                               text="link can: applying the station's commands (cmd)", measured=[0.2, 0.0],
                               engaged=True)}


def _in_process(port: int, robots: list[str]) -> dict[str, float]:
    """The tool's phases, ms: the session's opening and the ask until every node answered."""
    from bridge.tools.status import Seen, ask, complete

    t0 = time.perf_counter()
    with open_session(make_config(mode="client", connect=[tcp(port)])) as session:
        t1 = time.perf_counter()
        seen = Seen()
        ask(session, seen, [f"scm/{r}/status/*" for r in robots], 5.0)
        t2 = time.perf_counter()
        assert complete(seen, robots), "not every node answered the query"
    return {"session_open_ms": 1e3 * (t1 - t0), "ask_ms": 1e3 * (t2 - t1)}


def measure(robots: int, repeat: int, every: bool) -> dict:
    names = [f"bench{k}" for k in range(robots)]
    port = free_port()
    stop = threading.Event()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session:
        outs = {(r, n): StatusOut(session, M.status_key(r, n)) for r in names for n in ("station", "driver")}

        def publish() -> None:  # as the nodes do: each second
            seq = 0
            while not stop.is_set():
                for (r, n), out in outs.items():
                    st = _statuses(r)[n]
                    out.put(M.encode(M.Status(**{**{f: getattr(st, f) for f in st.__struct_fields__},
                                                 "stamp": time.monotonic(), "seq": seq})))
                seq += 1
                stop.wait(1.0)

        t = threading.Thread(target=publish, daemon=True)
        t.start()
        try:
            phases = [_in_process(port, names) for _ in range(repeat)]
            who = ["--all"] if every else ["--robots", ",".join(names)]
            calls, errors = [], []
            for _ in range(repeat):
                t0 = time.perf_counter()
                res = subprocess.run([sys.executable, "-m", "bridge", "status", *who, "--mode", "client",
                                      "--connect", tcp(port)], capture_output=True, text=True, timeout=60)
                calls.append(time.perf_counter() - t0)
                if res.returncode != 0:
                    errors.append(res.stderr.strip()[-300:] or res.stdout.strip()[-300:])
        finally:
            stop.set()
            t.join(5)
    call_ms = 1e3 * np.asarray(calls)
    return {
        "bench": "console", "robots": robots, "repeat": repeat, "asked": "--all" if every else "--robots",
        "status_call_ms": {"median": float(np.median(call_ms)), "max": float(call_ms.max())},
        "session_open_ms_median": float(np.median([p["session_open_ms"] for p in phases])),
        "ask_ms_median": float(np.median([p["ask_ms"] for p in phases])),
        "target_ms": 1e3 * TARGET_S, "within_target": bool(np.median(call_ms) < 1e3 * TARGET_S),
        "errors": errors,
    }


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--count", type=int, default=1, help="robots whose station and driver host answer")
    ap.add_argument("--repeat", type=int, default=5, help="status calls timed")
    ap.add_argument("--all", action="store_true", help="time `status --all` instead of `status --robots ...`")


def run(args: argparse.Namespace) -> int:
    if args.repeat < 1 or args.count < 1:
        from bridge.core.errors import UsageError

        raise UsageError("--repeat and --count must be at least 1")
    out = measure(args.count, args.repeat, args.all)
    emit(out)
    return 1 if out["errors"] else 0
