"""``scmbridge bench fuzz``: mutated input at every trust boundary, each receiver's count checked against what was sent.

Inputs (``--inputs``, all by default), ``--per-input N`` payloads each, seeded (``--seed``):

- ``zenoh_cmd``, ``zenoh_estop``: MessagePack payloads on ``scm/<robot>/cmd`` and ``scm/<robot>/estop`` into a real
  driver host process (``scmbridge driver --link can --emulate``) behind a Zenoh router in this process. The oracle
  is the wire contract (:func:`bridge.core.wire.decode`): the host's final status must count every payload that fails it
  in ``malformed_<input>`` and every other command in exactly one gate counter (``accepted`` or a refusal); for
  estops the latch counters (``estops``, ``estop_releases``, ``estop_release_refused``) must be what the documented
  latch rule gives for the valid ones, in order. Every ``applied`` echo is checked as it arrives: it decodes (finite,
  in wire range), it is inside the hard limits, a stop is exactly zero.
- ``udp_driver``, ``udp_robot``: datagrams at the UDP-shim driver (from its pinned robot address and from a
  stranger) and at the emulated robot (from its pinned peer and from a stranger), each on loopback ports bound here.
  Each side counts every datagram once: foreign, malformed (the wire contract), or one of its stream's verdicts.
- ``can_decoder``: frames straight into ``drivers.can.decode``; ``can_driver``: frames on a python-can ``virtual``
  channel at a running CAN driver, impersonating its controllers; ``can_ecu``: frames at the emulated controllers,
  impersonating the driver. The oracle is CANSimple as the shipped DBC lays it out (standard 11-bit id, a known
  command, the DBC's length, finite floats), read with ``struct``. A strict decoder counts every frame that is not
  CANSimple; an ODrive ignores some of them (unknown commands, other nodes, extended ids) without counting: for the
  controllers the count must be exactly the frames every device counts, or exactly those plus all the others.
- ``mavlink_driver``, ``mavlink_rover``: MAVLink bytes (UDP datagrams) at the driver's pymavlink parser (a scripted
  vehicle on a loopback port) and at the emulated rover. The oracle is a second pymavlink parser fed the same
  datagrams: the receiver's ``BAD_DATA`` count must equal the oracle's. Each datagram starts on a frame marker and
  leaves no partial frame behind, so the count does not depend on how the receiver's reads split the stream.

Mutations: random bytes; bit flips, truncations and extensions of valid encodings; valid structure with NaN, inf or
huge values; unknown fields; wrong types; missing fields; huge sequence numbers and epochs; long strings and arrays;
in between, valid messages of a real stream. After each input the vehicle side is checked (the emulated vehicle's
``SimVehicle.command`` calls, or the ``applied`` echoes): no non-finite or out-of-limits command, and a real
command still drives.

``rss_rounds_mb``: the driver host's RSS before and after each of ``--rounds`` rounds of ``--round-size`` Zenoh
``cmd`` payloads (a fresh process). ``rss_probe``: the same rounds against a driver-host-like process of this module
(a :class:`bridge.nodes.driver_host.DriverHost` with its Zenoh session and emulated controllers) that also reports the
Python heap (``tracemalloc``), glibc's heap (``mallinfo2``: in use, and free but kept) and its RSS after
``malloc_trim(0)``: where the growth is, and whether it is returned.
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.fuzz.can_link import can_decoder, can_driver, can_ecu
from bench.fuzz.host import fuzz_zenoh
from bench.fuzz.mavlink_link import mavlink_driver, mavlink_rover
from bench.fuzz.rss import probe_host, rss_rounds, rss_senders, rss_verdict
from bench.fuzz.udp_link import udp_driver, udp_robot
from bridge.core.errors import UsageError
from bridge.nodes.node import add_zenoh_args

#: every input, in the order they run
INPUTS = ("zenoh_cmd", "zenoh_estop", "udp_driver", "udp_robot", "can_decoder", "can_driver", "can_ecu",
          "mavlink_driver", "mavlink_rover")

IN_PROCESS: dict[str, Callable[[int, int, Path], dict]] = {
    "udp_driver": udp_driver, "udp_robot": udp_robot, "can_decoder": can_decoder, "can_driver": can_driver,
    "can_ecu": can_ecu, "mavlink_driver": mavlink_driver, "mavlink_rover": mavlink_rover}


def fuzz(per_input: int, seed: int, inputs: tuple[str, ...], workdir: Path, rounds: int = 0,
        round_size: int = 0, probe: bool = False, senders: int = 0, per_sender: int = 0) -> dict:
    """Every input asked for (``per_input`` payloads each), then the RSS rounds; one JSON-ready dict."""
    out: dict[str, Any] = {"per_input": per_input, "seed": seed, "inputs": {}}
    zenoh_inputs = tuple(i for i in inputs if i.startswith("zenoh_"))
    if zenoh_inputs:
        out["inputs"].update(fuzz_zenoh(per_input, seed, workdir, zenoh_inputs))
    for k, name in enumerate(inputs):
        if name in IN_PROCESS:
            out["inputs"][name] = IN_PROCESS[name](per_input, seed + 10 + k, workdir)
    res = out["inputs"]
    out["summary"] = {name: {"sent": r["sent"], "counted": r["counted"], "expected": r["expected"],
                             "exact": r["exact"], "crashes": r["crashes"],
                             "vehicle_ok": r.get("vehicle", {}).get("ok"),
                             "drives_after": r.get("drives_after", {}).get("ok"), "seconds": r["seconds"],
                             "rss_mb": [r["rss_mb"]["before"], r["rss_mb"]["after"]]} for name, r in res.items()}
    out["all_exact"] = all(r["exact"] for r in res.values())
    out["all_vehicle_ok"] = all(r.get("vehicle", {}).get("ok", True) for r in res.values())
    if rounds > 0:
        r = rss_rounds(rounds, round_size, seed + 100, workdir)
        out["rss_rounds_mb"] = r["rss_mb"]
        out["rss_rounds"] = r
        out["rss_rounds_shm_off"] = rss_rounds(rounds, round_size, seed + 100, workdir, shm=False)
        pr = on = off = None
        if probe:
            out["rss_probe"] = pr = rss_rounds(rounds, round_size, seed + 100, workdir, probe=True)
        if senders > 0:
            out["rss_senders"] = on = rss_senders(senders, per_sender, seed + 200, workdir)
            out["rss_senders_shm_off"] = off = rss_senders(senders, per_sender, seed + 200, workdir, shm=False)
        out["rss_verdict"] = rss_verdict(r, pr, on, off)
    return out


def arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--per-input", type=int, default=100_000, help="payloads per input (default 100000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--inputs", default=",".join(INPUTS), help=f"comma-separated subset of {', '.join(INPUTS)}")
    ap.add_argument("--rounds", type=int, default=5, help="RSS study: rounds of Zenoh cmd payloads (0: none)")
    ap.add_argument("--round-size", type=int, default=50_000, help="RSS study: payloads per round")
    ap.add_argument("--no-probe", action="store_true", help="RSS study without the heap-reporting probe host")
    ap.add_argument("--senders", type=int, default=4, help="RSS study: successive sender sessions (0: none)")
    ap.add_argument("--per-sender", type=int, default=2000, help="RSS study: 4-64 KiB payloads per sender")
    ap.add_argument("--probe-host", default=None, metavar="ROBOT", help=argparse.SUPPRESS)  # the RSS study's child
    add_zenoh_args(ap)


def run(args: argparse.Namespace) -> int:
    if args.probe_host:
        return probe_host(args)
    inputs = tuple(i.strip() for i in args.inputs.split(",") if i.strip())
    unknown = [i for i in inputs if i not in INPUTS]
    if unknown or args.per_input < 1 or args.rounds < 0:
        raise UsageError(f"unknown inputs {unknown}" if unknown else "--per-input >= 1 and --rounds >= 0")
    with tempfile.TemporaryDirectory(prefix="scm-fuzz-") as tmp:
        out = fuzz(args.per_input, args.seed, inputs, Path(tmp), args.rounds, args.round_size, not args.no_probe,
                  args.senders, args.per_sender)
    from bench.common import emit

    emit(out)
    return 0 if out["all_exact"] and out["all_vehicle_ok"] else 1
