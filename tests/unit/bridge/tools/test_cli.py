"""bridge/tools/cli.py: the command table and the dispatcher's own contract, in-process: markup made plain, the
table's words, modules and functions, group and unknown-command answers, and the exit statuses of a usage error
(2), a denial (3) and a termination (128 + the signal). Every parser's help and options, ``--version``, docs/CLI.md
and the missing-extra message are in tests/repo/test_cli.py."""

from __future__ import annotations

import json
import shutil
import signal
from collections import Counter

import pytest

from bridge.core.errors import Denied
from bridge.tools import cli, deploy


@pytest.fixture(autouse=True)
def _own_signals_and_env(monkeypatch: pytest.MonkeyPatch):
    """main() installs SIGTERM/SIGHUP handlers and sets one-BLAS-thread defaults: both are undone after each test."""
    for var in cli.ONE_BLAS_THREAD:
        monkeypatch.setenv(var, "1")
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)


def test_docstring_markup_is_made_plain_for_help() -> None:
    text = "Use ``--robot`` with :class:`~bridge.x.Y`, :func:`f` and :data:`Z`; **not** :meth:`a.b`."
    assert cli.plain(text) == "Use --robot with bridge.x.Y, f and Z; not a.b."


def test_every_command_is_named_once_and_groups_are_first_words_of_two() -> None:
    counts = Counter(c.name for c in cli.COMMANDS)
    assert max(counts.values()) == 1 and set(cli.BY_NAME) == set(counts)
    assert all(1 <= len(c.words) <= 2 and c.summary for c in cli.COMMANDS)
    assert {c.words[0] for c in cli.COMMANDS if len(c.words) == 2} == cli.GROUPS
    assert not cli.GROUPS & {c.name for c in cli.COMMANDS if len(c.words) == 1}  # a word is a group or a command


def test_a_two_word_command_uses_its_words_functions_when_its_module_has_them() -> None:
    class Several:
        def run_check(self): ...

    several = Several()
    assert cli.Command("config check", "m", "s").suffix(several) == "_check"
    assert cli.Command("config show", "m", "s").suffix(several) == ""  # no run_show: the plain names
    assert cli.Command("station", "m", "s").suffix(several) == ""


@pytest.mark.parametrize("cmd", [c for c in cli.COMMANDS if not c.module.startswith(("bench.", "sim_learner."))],
                         ids=lambda c: c.name)
def test_every_bridge_command_module_defines_its_functions(cmd: cli.Command) -> None:
    module = cli.load(cmd)
    suffix = cmd.suffix(module)
    assert callable(getattr(module, f"arguments{suffix}")) and callable(getattr(module, f"run{suffix}"))


def test_the_help_text_is_the_run_functions_docstring_else_the_modules() -> None:
    import types

    with_run = types.SimpleNamespace(__doc__="Module doc.", run_x=lambda: None)
    with_run.run_x.__doc__ = "Run ``x``.\n\n    Second paragraph."
    assert cli._description(with_run, "summary", "_x") == "Run x.\n\nSecond paragraph."
    assert cli._description(types.SimpleNamespace(__doc__="Module :mod:`m`."), "s", "") == "Module m."
    assert cli._description(types.SimpleNamespace(__doc__=None), "the summary", "") == "the summary"


def test_no_arguments_or_help_print_the_root_help(capsys) -> None:
    for argv in ([], ["-h"], ["--help"], ["help"]):
        assert cli.main(argv) == 0
        out = capsys.readouterr().out
        assert out.startswith("usage: scmbridge [--version] COMMAND [OPTIONS]") and "docs/CLI.md" in out


def test_a_group_lists_its_commands_and_an_unknown_one_is_exit_2(capsys) -> None:
    assert cli.main(["mission", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: scmbridge mission {start|pause|resume|abort|status|send|place} [OPTIONS]")
    assert cli.main(["mission", "fly"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("scmbridge: unknown command 'mission fly'") and "mission commands:" in err


def test_a_usage_error_is_one_line_and_exit_2(tmp_path, capsys) -> None:
    assert cli.main(["replay", str(tmp_path / "missing.mcap")]) == 2
    err = capsys.readouterr().err
    assert err == f"scmbridge replay: error: {tmp_path / 'missing.mcap'}: no such file\n"


def test_a_bad_option_is_argparses_exit_2() -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(["record", "--all", "--out", "x.mcap", "--max-bytes", "lots"])
    assert done.value.code == 2


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
def test_a_denial_is_one_line_and_its_own_exit_status(certs, tmp_path, capsys) -> None:
    conf = tmp_path / "observer.json5"  # the observer's certificate may not command a robot (calibrate publishes cmd)
    conf.write_text(json.dumps(deploy.client_config("observer", connect="tls/127.0.0.1:9", certs=certs.lab)))
    argv = ["calibrate", "--robot", "rover1", "--zenoh-config", str(conf), "--store", str(tmp_path / "p.bin")]
    assert cli.main(argv) == Denied.EXIT == 3
    err = capsys.readouterr().err
    assert err.startswith("scmbridge calibrate: denied: identity 'observer'") and err.count("\n") == 1


def test_a_termination_unwinds_like_ctrl_c_and_exits_128_plus_the_signal(monkeypatch, capsys) -> None:
    from bridge.tools import replay

    def killed(args):
        signal.raise_signal(signal.SIGTERM)  # the handler main() installed raises Terminated here
        raise AssertionError("not reached")

    monkeypatch.setattr(replay, "run", killed)
    assert cli.main(["replay", "x.mcap"]) == 128 + signal.SIGTERM
    assert capsys.readouterr().err == "scmbridge replay: SIGTERM: stopped\n"
    t = cli.Terminated(signal.SIGHUP)
    assert isinstance(t, KeyboardInterrupt) and t.signum == signal.SIGHUP and str(t) == "SIGHUP"


def test_main_gives_the_process_one_blas_thread_unless_told_otherwise(monkeypatch) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS")
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    assert cli.main(["--version"]) == 0
    import os

    assert os.environ["OMP_NUM_THREADS"] == "1" and os.environ["OPENBLAS_NUM_THREADS"] == "4"


def test_ctrl_c_raises_keyboardinterrupt_also_where_the_parent_ignored_sigint() -> None:
    """A tool started where SIGINT is ignored (a shell script's background job, a CI runner's step: Python keeps an
    inherited SIG_IGN) still stops on Ctrl-C: ``status --watch`` so started ran on after its Ctrl-C."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cli._terminate_like_ctrl_c()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)


def test_a_tool_that_only_talks_over_zenoh_starts_without_the_numerical_stack() -> None:
    """The operator's tools (mission, estop, engage, status) and the configuration they read load neither numpy nor
    the package metadata (only ``--version`` asks for it): every start of one stays cheap. In a fresh interpreter,
    since this one has both loaded."""
    import subprocess
    import sys

    mods = ["bridge.tools.cli", "bridge.tools.mission", "bridge.tools.estop", "bridge.tools.engage",
            "bridge.tools.status", "bridge.core.config"]
    code = (f"import sys; import {', '.join(mods)}; "
            "print(sorted(m for m in ('numpy', 'importlib.metadata') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stdout + done.stderr
