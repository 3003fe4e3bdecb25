"""The driver host's RSS under the Zenoh fuzz: rounds of ``cmd`` payloads into one host, successive sender
sessions, and a driver-host-like probe process that also reports its Python and glibc heaps."""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import random
import sys
import threading
import time
import tracemalloc
from pathlib import Path
from typing import Any

import msgspec

from bench.fuzz.harness import new_vehicle, wait_until
from bench.fuzz.host import HostRig, fuzz_cmd_payloads
from bridge.core.logsink import print_line
from bridge.nodes.node import rss_mb, rss_parts


def zenoh_segments(pid: int) -> int:
    """Zenoh shared-memory segments (``/dev/shm/*.zenoh``) mapped by ``pid``."""
    with contextlib.suppress(OSError), open(f"/proc/{pid}/maps") as f:
        return len({line.split()[-1] for line in f if line.rstrip().endswith(".zenoh")})
    return 0


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]


def _libc():
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        return libc
    except (OSError, AttributeError):  # not glibc, or a glibc older than 2.33
        return None


def heap_report(first: tracemalloc.Snapshot | None = None) -> dict:
    """This process's RSS, its Python heap as tracemalloc sees it, glibc's heap (all arenas) and, against the
    ``first`` snapshot, the five Python allocation sites that grew most."""
    mb = 1024 * 1024
    cur, peak = tracemalloc.get_traced_memory()
    out: dict[str, Any] = {"rss_mb": rss_mb(), "python_traced_mb": round(cur / mb, 2),
                           "python_traced_peak_mb": round(peak / mb, 2),
                           "tracemalloc_overhead_mb": round(tracemalloc.get_tracemalloc_memory() / mb, 2),
                           "threads": threading.active_count()}
    with contextlib.suppress(OSError), open("/proc/self/status") as f:
        out["os_threads"] = next((int(line.split()[1]) for line in f if line.startswith("Threads:")), None)
    libc = _libc()
    if libc is not None:
        mi = libc.mallinfo2()
        out.update({"malloc_in_use_mb": round((mi.uordblks + mi.hblkhd) / mb, 2),
                    "malloc_free_kept_mb": round(mi.fordblks / mb, 2),
                    "malloc_heap_mb": round(mi.arena / mb, 2), "malloc_mmapped_mb": round(mi.hblkhd / mb, 2)})
    if first is not None:
        diff = tracemalloc.take_snapshot().compare_to(first, "lineno")[:5]
        out["python_top_growth"] = [{"where": str(d.traceback[0]), "kb": round(d.size_diff / 1024, 1),
                                     "count": d.count_diff} for d in diff]
    return out


def probe_host(args: argparse.Namespace) -> int:
    """A driver-host-like process for the RSS study: the real
    :class:`bridge.nodes.driver_host.DriverHost` with its Zenoh
    session and the emulated CAN controllers in-process (as ``scmbridge driver --link can --emulate``), under
    tracemalloc. Lines on stdin: ``measure`` prints ``PROBE {json}`` (:func:`heap_report`), ``trim`` calls glibc's
    ``malloc_trim(0)`` first, ``quit`` stops it."""
    import logging

    from bridge.nodes.driver_config import load_driver
    from bridge.nodes.driver_host import DriverHost
    from bridge.nodes.node import stop_on_signals, zenoh_config
    from bridge.nodes.zsession import open_session
    from drivers import open_driver
    from sim_learner.can_ecu import DiffDriveEcus

    args.robot = args.probe_host
    logging.basicConfig(level=logging.ERROR)
    tracemalloc.start(1)
    cfg = load_driver(None)
    link = msgspec.structs.replace(cfg.link.can, interface="virtual", channel=f"scm-{args.robot}")
    host = DriverHost(cfg, "can", open_driver("can", link), args.robot, cfg.driver.rate_hz)
    host.options.engage_on_start = True  # as `scmbridge driver --engage`
    ecus = DiffDriveEcus({"interface": "virtual", "channel": link.channel}, new_vehicle(),
                         left_node=link.left_node, right_node=link.right_node, left_sign=link.left_sign,
                         right_sign=link.right_sign, wheel_radius=link.wheel_radius,
                         track_width=link.track_width).start()
    stop = stop_on_signals()
    first: list[tracemalloc.Snapshot] = []

    def control() -> None:
        for line in sys.stdin:
            word = line.strip()
            if word == "quit":
                break
            if word == "trim" and _libc() is not None:
                _libc().malloc_trim(0)
            if not first:
                first.append(tracemalloc.take_snapshot())
            print_line("PROBE " + json.dumps(heap_report(first[0])))
        stop.set()

    threading.Thread(target=control, name="probe-control", daemon=True).start()
    try:
        with open_session(zenoh_config(args)) as session:
            host.serve(session, stop, None)
    finally:
        host.driver.close()
        ecus.stop()
    return 0


def _probe(rig: HostRig, word: str = "measure") -> dict:
    rig.proc.stdin.write(word + "\n")
    rig.proc.stdin.flush()
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        line = rig.proc.stdout.readline()
        if not line:
            break
        if line.startswith("PROBE "):
            return json.loads(line[6:])
    raise RuntimeError("the probe host did not answer")


def rss_rounds(rounds: int, size: int, seed: int, workdir: Path, probe: bool = False, shm: bool = True) -> dict:
    """The ``cmd`` fuzz in ``rounds`` rounds of ``size`` into one fresh host; RSS (and its parts) before and after
    each round; with ``probe``, the host's heap too, and what ``malloc_trim(0)`` returns at the end."""
    rng = random.Random(seed)
    robot = f"fuzzrss{'p' if probe else ''}{'' if shm else 'n'}{os.getpid()}"
    with HostRig(workdir, robot, probe=probe, shm=shm) as rig:
        time.sleep(1.0)
        out: dict[str, Any] = {"rss_mb": [rig.rss()], "parts_mb": [rss_parts(rig.proc.pid)], "exact": []}
        if probe:
            out["heap"] = [_probe(rig)]
        for _ in range(rounds):
            res = fuzz_cmd_payloads(rig, size, rng)
            time.sleep(1.0)
            out["rss_mb"].append(rig.rss())
            out["parts_mb"].append(rss_parts(rig.proc.pid))
            out["exact"].append(res["exact"])
            if probe:
                out["heap"].append(_probe(rig))
        if probe:
            out["after_malloc_trim"] = _probe(rig, "trim")
        out["crashes"] = rig.crashes()
    r = out["rss_mb"]
    steps = [round(b - a, 1) for a, b in zip(r, r[1:])]
    out["growth_per_round_mb"] = steps
    growth = r[-1] - r[0]
    out["trend"] = "plateau" if len(steps) >= 3 and max(steps[-2:]) <= max(1.0, 0.1 * growth) else "growing"
    return out


def rss_senders(senders: int, per_sender: int, seed: int, workdir: Path, shm: bool = True) -> dict:
    """``senders`` Zenoh sessions one after the other (a station restarted, a tool run on the same machine), each
    putting ``per_sender`` payloads of 4-64 KiB on ``cmd`` (above Zenoh's 3072-byte shared-memory threshold) and
    closing: the host's RSS, its parts and the Zenoh segments it maps after each, and 10 s after the last.
    ``shm``: every session with Zenoh's shared-memory transport on (zenoh's default) or off (scmbridge's)."""
    import zenoh

    from bridge.nodes.zsession import make_config, open_session

    rng = random.Random(seed)
    with HostRig(workdir, f"fuzzsnd{'' if shm else 'n'}{os.getpid()}", shm=shm) as rig:
        pid = rig.proc.pid
        time.sleep(1.0)
        rows = [{"after_sender": 0, **rss_parts(pid), "zenoh_segments": zenoh_segments(pid)}]
        before = rig.counters().get("malformed_cmd", 0)
        for k in range(senders):
            conf = make_config(mode="client", connect=[rig.endpoint])
            conf.insert_json5("transport/shared_memory/enabled", json.dumps(shm))  # as the host's
            with open_session(conf) as s:
                pub = s.declare_publisher(rig.keys.cmd, congestion_control=zenoh.CongestionControl.BLOCK)
                time.sleep(0.3)
                for _ in range(per_sender):
                    pub.put(rng.randbytes(rng.randint(4096, 65536)))
                wait_until(lambda n=(k + 1) * per_sender: rig.counters().get("malformed_cmd", 0) - before >= n,
                           30.0, 0.05)
            time.sleep(1.0)
            rows.append({"after_sender": k + 1, **rss_parts(pid), "zenoh_segments": zenoh_segments(pid)})
        time.sleep(10.0)
        rows.append({"after_sender": senders, "waited_s": 10, **rss_parts(pid), "zenoh_segments": zenoh_segments(pid)})
        counted = rig.status_after(time.monotonic()).get("malformed_cmd", 0) - before
    per = sorted(b["rss"] - a["rss"] for a, b in zip(rows[1:], rows[2:-1]))
    return {"shared_memory": shm, "rows": rows, "counted_exactly": counted == senders * per_sender,
            "rss_per_further_sender_mb": round(per[len(per) // 2], 1) if per else None}  # the median


def rss_verdict(rounds: dict, probe: dict | None, senders_on: dict | None, senders_off: dict | None) -> dict:
    """The numbers that say where the growth is and whether it is bounded."""
    p0, p1 = rounds["parts_mb"][0], rounds["parts_mb"][-1]
    out: dict[str, Any] = {
        "one_sender": {"trend": rounds["trend"], "rss_mb": [rounds["rss_mb"][0], rounds["rss_mb"][-1]],
                       "growth_mb": {k: round(p1.get(k, 0) - p0.get(k, 0), 1) for k in ("rss", "anon", "file",
                                                                                            "shmem")}}}
    if probe is not None:
        h0, h1, ht = probe["heap"][0], probe["heap"][-1], probe["after_malloc_trim"]
        out["heap"] = {k: [h0.get(k), h1.get(k)] for k in ("python_traced_mb", "malloc_in_use_mb",
                                                           "malloc_free_kept_mb", "os_threads")}
        out["heap"]["rss_returned_by_malloc_trim_mb"] = round(h1["rss_mb"] - ht["rss_mb"], 1)
    for name, res in (("senders_shm_on", senders_on), ("senders_shm_off", senders_off)):
        if res is not None:
            out[name] = {"rss_per_further_sender_mb": res["rss_per_further_sender_mb"],
                         "zenoh_segments": [r["zenoh_segments"] for r in res["rows"]],
                         "shmem_mb": [r.get("shmem") for r in res["rows"]]}
    return out
