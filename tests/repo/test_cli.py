"""One grammar for every command: each --help exits 0 with plain text, every option follows the naming rules
(durations are --duration in seconds, answers are awaited for --timeout seconds, --robot/--robots are names), and
docs/CLI.md is exactly what the parsers say."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bridge.core.args import robot_arg, robots_arg
from bridge.tools import cli

ROOT = Path(__file__).resolve().parents[2]
#: option names that once meant a duration; every one is now --duration (or --timeout for a wait on an answer)
OLD_DURATIONS = {"--seconds", "--minutes", "--max-time", "--link-seconds", "--sample-s", "--warmup-s", "--flush-s"}


@pytest.mark.parametrize("name", [c.name for c in cli.COMMANDS])
def test_every_help_is_plain_text_and_every_option_follows_the_naming_rules(name: str, capsys) -> None:
    cmd = cli.BY_NAME[name]
    parser = cli.parser_for(cmd)
    with pytest.raises(SystemExit) as done:
        cli.main([*cmd.words, "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: scmbridge {name}"), text[:200]
    assert not re.search(r"``|:class:|:func:|:mod:|\*\*\w", text), f"markup in the help of {name}"
    assert "--log-level" in text
    for action in parser._actions:
        for opt in action.option_strings:
            assert opt not in OLD_DURATIONS and not opt.endswith("-s"), f"{name}: {opt} (a duration is --duration)"
        if action.dest == "robot" and action.option_strings:
            assert action.type is robot_arg, f"{name}: --robot is one robot name"
        if action.dest == "robots" and action.option_strings:
            assert action.type is robots_arg, f"{name}: --robots is a list of names"


def test_groups_version_and_unknown_commands() -> None:
    run = [sys.executable, "-m", "bridge"]
    res = subprocess.run([*run, "--version"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and re.fullmatch(r"scmbridge \d+\.\d+\.\d+\S*\n", res.stdout)
    res = subprocess.run([*run, "bench", "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "bench fleet" in res.stdout
    res = subprocess.run([*run, "bench"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "usage: scmbridge bench" in res.stderr
    res = subprocess.run([*run, "nonsense"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "unknown command 'nonsense'" in res.stderr
    res = subprocess.run([*run, "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and all(c.name in res.stdout for c in cli.COMMANDS)


def test_the_cli_reference_is_current() -> None:
    doc = (ROOT / "docs" / "CLI.md").read_text()
    assert doc == cli.reference(), "docs/CLI.md is stale: run `make cli-doc`"


def test_parsers_refuse_names_that_are_not_robot_names() -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        robot_arg("a/b")
    with pytest.raises(argparse.ArgumentTypeError):
        robots_arg("a,a")
    assert robots_arg("r1, r2") == ["r1", "r2"]


def test_numba_caches_in_the_cache_directory_when_the_install_is_not_writable(tmp_path, monkeypatch) -> None:
    """Finding: as the service user of a root-owned install, `station --help` failed: numba could not cache its
    kernels next to their source. The CLI then points numba at the cache directory (systemd's CacheDirectory=)."""
    from bridge.tools import cli

    ro = tmp_path / "scm"
    ro.mkdir()
    monkeypatch.setenv("NUMBA_CACHE_DIR", "")  # recorded, so the test's value is undone afterwards
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("SCMBRIDGE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(cli.os, "access", lambda path, mode: False)  # what a non-root user finds
    assert cli.numba_cache_dir(ro) == str(tmp_path / "cache" / "numba") == cli.os.environ["NUMBA_CACHE_DIR"]
    assert cli.numba_cache_dir(ro) is None  # set once: a person's own NUMBA_CACHE_DIR is never overridden


def test_a_missing_extra_says_which_to_install(monkeypatch, capsys) -> None:
    """Finding: a missing extra gave a raw traceback (`No module named 'foxglove'`)."""
    import builtins

    from bridge.tools import cli

    real = builtins.__import__

    def no_foxglove(name, *args, **kwargs):
        if name == "foxglove" or name.startswith("foxglove."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return real(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "bridge.tools.live", raising=False)
    monkeypatch.setattr(builtins, "__import__", no_foxglove)
    assert cli.main(["view", "--robot", "r1", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "needs foxglove, in the 'station' extra" in err and "Traceback" not in err


def test_importing_the_cli_changes_nothing_in_the_process() -> None:
    """The environment (one BLAS thread, numba's cache) is set by ``main()``, not by an import: a program or a test
    that imports a command's module keeps its own environment."""
    code = ("import os; before = dict(os.environ); import bridge.tools.cli; "
            "assert dict(os.environ) == before, set(os.environ.items()) ^ set(before.items())")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                              "MKL_NUM_THREADS", "NUMBA_CACHE_DIR")}
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
