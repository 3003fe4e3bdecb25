"""The ``scmbridge`` command: one grammar for every command (its reference is docs/CLI.md, generated from here).

Every command, one word (``station``) or two (``config check``, ``bench fleet``), is one entry of
:data:`COMMANDS` naming the module that implements it. That module defines ``arguments(parser)`` (its options)
and ``run(args) -> int`` (for a two-word command ``arguments_<word>`` and ``run_<word>``). Only the module of the
command asked for is imported. Every command takes ``--log-level`` and ``--help``; ``scmbridge --version``.
Expected failures end with one line and exit status 2 (:class:`UsageError`, a configuration error); what the lab's
access control denies, with exit status 3 (:class:`~bridge.core.errors.Denied`).
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import inspect
import os
import re
import shlex
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.core import logsink
from bridge.core.errors import Denied, UsageError

# The numerical work here is small matrices (a 20-step MPC, 2 x 2 maps): OpenBLAS's default worker threads only
# spin between calls and steal the CPU other stations and the driver host need. main() sets it before any command
# imports numpy (importing this module changes nothing); an explicit setting in the environment wins.
#: one BLAS / OpenMP thread: what every station process runs with (the shipped units set it too)
ONE_BLAS_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


#: optional modules and the smallest extra that brings each (pyproject.toml)
EXTRA_OF = {"foxglove": "station", "mcap": "record", "casadi": "station", "numba": "station", "scipy": "station",
            "matplotlib": "sims"}
#: the station side's install from the source tree: the full lock, hash-checked, then the project offline (the
#: Makefile's bootstrap; `pip install --no-deps '.[station]'` cannot work: --no-deps drops the extra's packages)
FULL_INSTALL = ("pip install --require-hashes --only-binary=:all: -r requirements/dev.txt && "
                "pip install --no-deps --no-build-isolation .")
#: where the SC kernels live (numba caches next to them when it may)
KERNELS_DIR = Path(__file__).resolve().parents[2] / "transfer" / "scm"


def numba_cache_dir(kernels: Path = KERNELS_DIR) -> str | None:
    """Where numba caches the SC kernels when it cannot next to their source (an install owned by root, run by a
    service user): the cache directory, unless ``NUMBA_CACHE_DIR`` is set. Set before numba is first imported
    (this module runs first for every command); without it numba fails at import: "cannot cache function"."""
    if os.environ.get("NUMBA_CACHE_DIR") or os.access(kernels, os.W_OK):
        return None
    from bridge.core.paths import cache_dir

    os.environ["NUMBA_CACHE_DIR"] = str(cache_dir() / "numba")
    return os.environ["NUMBA_CACHE_DIR"]


LOG_LEVELS = ("debug", "info", "warning", "error")
WIDTH = 110  # help text width: fixed, so docs/CLI.md does not depend on the terminal


@dataclass(frozen=True)
class Command:
    """One command: its words, the module implementing it and a one-line summary."""

    name: str
    module: str
    summary: str

    @property
    def words(self) -> list[str]:
        return self.name.split()

    def suffix(self, module: Any) -> str:
        """The module's function names for this command: ``arguments_check``/``run_check`` for ``config check`` when
        the module defines them (one module for several commands), else ``arguments``/``run``."""
        sub = "_" + self.words[-1]
        return sub if len(self.words) == 2 and hasattr(module, f"run{sub}") else ""


_C = Command
#: every command, in the order ``scmbridge --help`` lists them
COMMANDS: list[Command] = [
    _C("demo", "bridge.tools.demo", "station + driver host + emulated learner over Zenoh on 127.0.0.1 (the S-path)"),
    _C("router", "bridge.nodes.router", "the lab's Zenoh router, a process of its own: every node is its client"),
    _C("station", "bridge.nodes.station", "the base-station service: teacher + transfer loop publishing commands"),
    _C("driver", "bridge.nodes.driver_cmd", "the driver host: Zenoh commands -> vehicle link, telemetry -> state"),
    _C("learner", "sim_learner.emulator", "a software learner behind a vehicle link, as its own process"),
    _C("calibrate", "bridge.tools.calibrate", "the calibration stage: a bounded grid of learner commands"),
    _C("doctor", "bridge.tools.doctor", "preflight: router, certificates, access rules, CAN, vehicle and failsafe"),
    _C("status", "bridge.tools.status", "why is it (not) moving: one line per robot and node"),
    _C("estop", "bridge.tools.estop", "stop one robot or every robot now, or release the latch, and confirm"),
    _C("engage", "bridge.tools.engage", "a person hands a robot's vehicle to the system (or takes it back)"),
    _C("mission start", "bridge.tools.mission", "start a robot's mission (a station starts idle)"),
    _C("mission pause", "bridge.tools.mission", "pause the running mission (stops until resumed)"),
    _C("mission resume", "bridge.tools.mission", "resume a paused mission (refused while the robot is not fit)"),
    _C("mission abort", "bridge.tools.mission", "abort the mission (stopped until a new start)"),
    _C("mission status", "bridge.tools.mission", "where the mission is and why"),
    _C("mission send", "bridge.tools.mission", "load a new mission into a station (idle until started)"),
    _C("mission place", "bridge.tools.mission_place", "a mission put where the robot stands now, in its poses' frame"),
    _C("view", "bridge.tools.live", "a live view of robots in Foxglove (a WebSocket server)"),
    _C("record", "bridge.tools.record", "record scm/** (or some robots) into an MCAP file"),
    _C("replay", "bridge.tools.replay", "republish a recording on its Zenoh keys"),
    _C("report", "bridge.tools.report", "the run's figures and summary from a recording"),
    _C("pairs show", "bridge.tools.pairs_cli", "print what a station learned: refined pairs and limits"),
    _C("pairs plot", "bridge.tools.pairs_cli", "draw what a station learned on both command domains"),
    _C("config check", "bridge.tools.config_cmd", "validate a station, driver or mission file"),
    _C("config show", "bridge.tools.config_cmd", "print a commented default configuration"),
    _C("keys udp", "bridge.tools.keys", "make the UDP link's datagram key (state directory, mode 0600)"),
    _C("keys mavlink", "bridge.tools.keys", "make the MAVLink 2 signing key (state directory, mode 0600)"),
    _C("deploy lab", "bridge.tools.deploy", "a whole secure lab in one command: CA, certificates, router and clients"),
    _C("deploy acl", "bridge.tools.deploy", "the base station router's TLS + access-control Zenoh config"),
    _C("deploy client", "bridge.tools.deploy", "a client's TLS Zenoh config (a robot, the operator)"),
    _C("deploy certs", "bridge.tools.deploy", "a throwaway CA and certificates (tests, a first try)"),
    _C("sim mpc", "sim_learner.experiments", "the paper's MPC simulation (or a seed sweep)"),
    _C("sim grid", "sim_learner.experiments", "the paper's exhaustive grid test of a learned store"),
    _C("sim primitives", "sim_learner.experiments", "the paper's motion-primitive simulation"),
    _C("sim drift", "sim_learner.drift", "a learner that changes mid-run: battery, payload, wheel, floor (JSON)"),
    _C("bench scm", "bench.scm", "Schwarz-Christoffel map build and evaluation timings (JSON)"),
    _C("bench transfer", "bench.transfer", "transfer policy cost per command (JSON)"),
    _C("bench mpc", "bench.mpc", "MPC solve times and closed-loop results per solver (JSON)"),
    _C("bench bridge", "bench.bridge", "end-to-end latency and 50 Hz loop jitter over Zenoh (JSON)"),
    _C("bench fleet", "bench.fleet", "how many robots one base station holds at 10 Hz (JSON)"),
    _C("bench tick", "bench.tick", "one station tick's CPU time by phase, in-process (JSON)"),
    _C("bench fuzz", "bench.fuzz.main", "mutated input at every trust boundary, counts checked exactly (JSON)"),
    _C("bench soak", "bench.soak", "the HIL loop driving for a long time: RSS trend, deadlines (JSON)"),
    _C("bench attack", "bench.attack", "every attack found, against the real components: what got through (JSON)"),
    _C("bench figures", "bench.figures", "the figures the docs quote, measured again by one command (JSON, table)"),
    _C("bench pairing", "bench.pairing", "a link's command pairs against the learner's true response (JSON)"),
    _C("bench estop", "bench.estop", "estop publish to the first applied stop, with the host's fsyncs slowed (JSON)"),
    _C("bench console", "bench.console", "how long the operator's status takes when every node answers (JSON)"),
    _C("bench sitl", "bench.sitl", "the transfer on a family of ArduPilot Rover profiles, per profile (JSON, table)"),
    _C("bench perf", "bench.perf", "the quick benchmarks judged against their targets: CI's regression guard (JSON)"),
]
BY_NAME = {c.name: c for c in COMMANDS}
GROUPS = {c.words[0] for c in COMMANDS if len(c.words) == 2}


def plain(text: str) -> str:
    """Docstring markup (``code``, :class:`x`, **bold**) as plain text for ``--help``."""
    text = re.sub(r":(?:class|func|mod|meth|data|attr):`~?([^`]+)`", r"\1", text)
    return text.replace("``", "").replace("**", "")


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions keep their paragraphs; everything is wrapped at :data:`WIDTH` whatever the terminal."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, width=WIDTH, max_help_position=32)


def version() -> str:
    from importlib import metadata  # here, not at the top: only --version asks, and every command starts here

    try:
        return metadata.version("scmbridge")
    except metadata.PackageNotFoundError:
        return "unknown"


def _description(module: Any, summary: str, suffix: str) -> str:
    """The command's help text: its ``run`` function's docstring (or its module's), as plain text."""
    fn = getattr(module, f"run{suffix}", None)
    doc = (fn.__doc__ if fn is not None and fn.__doc__ else module.__doc__) or summary
    return plain(inspect.cleandoc(doc))


def _bench_tree() -> None:
    """Benchmarks live in the source tree's top-level ``bench/``, not in the installed package: put that tree on
    the import path, or raise :class:`UsageError` saying where to run them from."""
    tree = Path(__file__).resolve().parents[2]
    if not (tree / "bench" / "__init__.py").exists():
        raise UsageError("the benchmarks ship with the source tree (bench/), not with the installed package: "
                         "run them from a clone")
    if str(tree) not in sys.path:
        sys.path.insert(0, str(tree))


def load(cmd: Command) -> Any:
    """The module implementing ``cmd``."""
    if cmd.module.startswith("bench."):
        _bench_tree()
    return importlib.import_module(cmd.module)


def parser_for(cmd: Command, module: Any | None = None) -> argparse.ArgumentParser:
    """The full parser of one command (its module's options plus ``--log-level``)."""
    module = module if module is not None else load(cmd)
    suffix = cmd.suffix(module)
    p = argparse.ArgumentParser(prog=f"scmbridge {cmd.name}", description=_description(module, cmd.summary, suffix),
                                formatter_class=_Formatter, allow_abbrev=False)
    getattr(module, f"arguments{suffix}")(p)
    p.add_argument("--log-level", choices=LOG_LEVELS, default="info", help="what is logged (default info)")
    return p


def _listing(names: list[Command], title: str) -> str:
    lines = [title, ""]
    lines += [f"  {c.name:<18} {c.summary}" for c in names]
    return "\n".join(lines)


def root_help() -> str:
    return "\n".join([
        "usage: scmbridge [--version] COMMAND [OPTIONS]", "",
        "Teacher-to-learner command transfer with Schwarz-Christoffel maps, bridged to robots over Zenoh.", "",
        _listing(COMMANDS, "commands:"), "",
        "Every command takes --help and --log-level {debug,info,warning,error}.",
        "The reference of every command and option: docs/CLI.md."])


def group_help(group: str) -> str:
    subs = [c for c in COMMANDS if c.words[0] == group]
    names = "|".join(c.words[1] for c in subs)
    return f"usage: scmbridge {group} {{{names}}} [OPTIONS]\n\n" + _listing(subs, f"{group} commands:")


def setup_logging(level: str, name: str) -> None:
    """The process's log at ``level``, written by a thread of its own so that no loop waits on stderr
    (:mod:`bridge.core.logsink`)."""
    logsink.setup(level, f"%(asctime)s {name.replace(' ', '-')} %(levelname)s %(message)s")


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread as Ctrl-C is: every ``with Children()`` and ``finally`` on the way
    out runs, so a tool killed by ``timeout``, CI or a closing terminal stops every process it started, as Ctrl-C
    does (a node replaces this with its own handler: :func:`bridge.nodes.node.stop_on_signals`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _terminate_like_ctrl_c() -> None:
    def handler(signum: int, _frame: object) -> None:
        raise Terminated(signum)

    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, handler)
    # Ctrl-C raises KeyboardInterrupt also where the parent ignored SIGINT (a shell script's background job, some CI
    # runners' steps): Python keeps an inherited SIG_IGN, and a `status --watch` started so ran on after its Ctrl-C
    signal.signal(signal.SIGINT, signal.default_int_handler)
    # `kill -USR2 PID`: every thread's Python stack on stderr, the process going on (where a command that does not
    # stop is waiting: docs/OPERATING.md)
    try:
        faulthandler.register(signal.SIGUSR2, file=sys.__stderr__, all_threads=True)
    except (AttributeError, ValueError, OSError):  # a stderr without a file descriptor: nowhere to print them
        pass


def main(argv: list[str] | None = None) -> int:
    """Dispatch to the command's module; returns the process exit code. The process's environment is set here,
    before any command imports numpy or numba: one BLAS thread and numba's cache directory."""
    for var, val in ONE_BLAS_THREAD.items():
        os.environ.setdefault(var, val)
    numba_cache_dir()
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "help"):
        print(root_help())
        return 0
    if args[0] == "--version":
        print(f"scmbridge {version()}")
        return 0
    word = args[0]
    if word in GROUPS:
        if len(args) < 2 or args[1] in ("-h", "--help"):
            print(group_help(word), file=sys.stdout if len(args) >= 2 else sys.stderr)
            return 0 if len(args) >= 2 else 2
        name, rest = f"{word} {args[1]}", args[2:]
        if name not in BY_NAME:
            print(f"scmbridge: unknown command {name!r}\n\n{group_help(word)}", file=sys.stderr)
            return 2
    elif word in BY_NAME:
        name, rest = word, args[1:]
    else:
        print(f"scmbridge: unknown command {word!r}\n\n{root_help()}", file=sys.stderr)
        return 2
    cmd = BY_NAME[name]
    _terminate_like_ctrl_c()
    try:
        module = load(cmd)
        ns = parser_for(cmd, module).parse_args(rest)
        ns.command_line = shlex.join(["scmbridge", *cmd.words, *rest])  # what a generated file says made it
        setup_logging(ns.log_level, name)
        return int(getattr(module, f"run{cmd.suffix(module)}")(ns) or 0)
    except Denied as exc:  # the lab's access control denies it: one line, its own exit status
        _err(f"scmbridge {name}: {exc}")
        return Denied.EXIT
    except UsageError as exc:  # a person's mistake or an expected failure: one line, no traceback
        _err(f"scmbridge {name}: error: {exc}")
        return 2
    except ModuleNotFoundError as exc:  # an install without this command's extra (a robot's base install)
        extra = EXTRA_OF.get((exc.name or "").split(".")[0])
        if extra is None:
            raise
        _err(f"scmbridge {name}: error: this command needs {exc.name}, in the '{extra}' extra, which a robot's "
             f"install leaves out; it runs on a station computer, installed from the full lock: `{FULL_INSTALL}` "
             "(README.md, Set-up)")
        return 2
    except Terminated as exc:
        _err(f"scmbridge {name}: {exc}: stopped")
        return 128 + exc.signum
    except KeyboardInterrupt:
        return 130
    except BaseException:
        logsink.flush()  # a traceback after the log lines written before it
        raise


def _err(text: str) -> None:
    """The command's one-line error on stderr, after every log line before it (:func:`bridge.core.logsink.flush`)."""
    logsink.flush()
    print(text, file=sys.stderr)


def reference() -> str:
    """docs/CLI.md: every command's help page, generated from the parsers (``make cli-doc``)."""
    out = ["# scmbridge command reference", "",
           "Generated from the parsers by `make cli-doc` (tests/repo/test_cli.py checks it is current).", "",
           "```", root_help(), "```", ""]
    for cmd in COMMANDS:
        out += [f"## scmbridge {cmd.name}", "", "```", parser_for(cmd).format_help().rstrip(), "```", ""]
    return "\n".join(out)


if __name__ == "__main__":
    sys.exit(main())
