"""The ``scmbridge`` command.

Subcommands are resolved lazily: only the module of the command asked for is imported (``import casadi`` or
``pymavlink`` cost a noticeable fraction of a second each). Every command module exposes
``main(argv: list[str]) -> int`` with its own argparse parser. A configuration mistake
(:class:`bridge.core.config.ConfigError`) ends the command with exit status 2 and one line naming the file, the key and
the problem; commands read their configuration before they open any link or session.
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

# The numerical work here is small matrices (a 20-step MPC, 2 x 2 maps): OpenBLAS's default worker threads only
# spin between calls (one station: 22-32 ms of CPU per tick against 9-15 ms single-threaded) and steal the CPU other
# stations and the driver host need. Set before anything imports numpy; an explicit setting in the environment wins.
#: one BLAS / OpenMP thread: what every station process runs with (the shipped units set it too)
ONE_BLAS_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
for _var, _val in ONE_BLAS_THREAD.items():
    os.environ.setdefault(_var, _val)

#: command -> (module, one-line help). ``bench`` and ``sim`` take a second word.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("bridge.tools.demo", "station + driver host + emulated learner over Zenoh on 127.0.0.1 (MPC S-path)"),
    "station": ("bridge.nodes.station", "the base-station service: teacher + transfer loop publishing commands"),
    "driver": ("bridge.nodes.driver_host", "the driver host: Zenoh commands -> vehicle link, telemetry -> state"),
    "learner": ("sim_learner.emulator", "a software learner behind a vehicle link (can, mavlink, udp)"),
    "sim": ("sim_learner.experiments", "the paper's simulations: sim primitives|mpc|grid --out DIR"),
    "calibrate": ("bridge.tools.calibrate", "the calibration stage: a bounded grid of learner commands into the store"),
    "view": ("bridge.tools.live", "a live view of robots in Foxglove (WebSocket server; --mcap writes the same)"),
    "estop": ("bridge.tools.estop",
              "estop --robot R|--all [--release --source NAME]: stop now, or release, and confirm"),
    "config": ("bridge.core.config", "config check FILE | config show --kind station|driver|mission"),
    "pairs": ("bridge.tools.pairs_cli", "see what was learned: pairs show|plot --robot R | --store FILE"),
    "deploy": ("bridge.tools.deploy", "deploy acl|client|certs: the lab's TLS + access-control Zenoh configs"),
    "bench scm": ("bench.scm", "Schwarz-Christoffel map build/evaluate timings (JSON)"),
    "bench transfer": ("bench.transfer", "transfer policy per-command cost (JSON)"),
    "bench mpc": ("bench.mpc", "MPC closed-loop solve times (JSON)"),
    "bench bridge": ("bench.bridge", "end-to-end latency and 50 Hz loop jitter over Zenoh (JSON)"),
    "record": ("bridge.tools.record", "record scm/** (or one robot) into an MCAP file, with schemas"),
    "replay": ("bridge.tools.replay", "republish a recording on its Zenoh keys at the recorded pace (or faster)"),
    "report": ("bridge.tools.report", "figures and the demo's summary figures from a recording"),
    "bench fleet": ("bench.fleet", "how many robots one base station holds at 10 Hz, N stations (JSON)"),
    "bench fuzz": ("bench.fuzz", "mutated input at every trust boundary, counts checked exactly; RSS (JSON)"),
    "bench soak": ("bench.soak", "the HIL loop driving the mission for --minutes: RSS trend, deadlines (JSON)"),
    "bench pairing": ("bench.pairing", "a link's command pairs against the learner's true response (JSON)"),
}


def _usage() -> str:
    lines = ["usage: scmbridge COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<16} {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "Run `scmbridge COMMAND --help` for a command's options."]
    return "\n".join(lines)


def _bench_path() -> str:
    """Benchmarks live in the source tree's top-level ``bench/`` (not in the installed product): put that tree on
    the import path, or say why it cannot be found."""
    tree = Path(__file__).resolve().parents[2]
    if not (tree / "bench" / "__init__.py").exists():
        return "the benchmarks ship with the source tree (bench/), not with the installed package: run from a clone"
    if str(tree) not in sys.path:
        sys.path.insert(0, str(tree))
    return ""


def main(argv: list[str] | None = None) -> int:
    """Dispatch to the command module; returns the process exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    name, rest = args[0], args[1:]
    if name == "bench":
        if not rest or rest[0].startswith("-"):
            benches = ",".join(n.split()[1] for n in COMMANDS if n.startswith("bench "))
            print(f"usage: scmbridge bench {{{benches}}} [OPTIONS]", file=sys.stderr)
            return 2
        name, rest = f"bench {rest[0]}", rest[1:]
    if name not in COMMANDS:
        print(f"scmbridge: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    from bridge.core.config import ConfigError

    target = COMMANDS[name][0]
    if target.startswith("bench."):
        err = _bench_path()
        if err:
            print(f"scmbridge {name}: error: {err}", file=sys.stderr)
            return 2
    module = importlib.import_module(target)
    try:
        return int(module.main(rest) or 0)
    except ConfigError as exc:  # a user's mistake: one line, no traceback
        print(f"scmbridge {name}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
