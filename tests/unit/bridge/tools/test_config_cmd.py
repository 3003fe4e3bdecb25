"""``scmbridge config check|show`` (:mod:`bridge.tools.config_cmd`): the struct of each kind, each value's TOML form
(read back by a TOML parser), the description of a key from its type, what ``check`` says of a valid file of each
kind (guessed or named), and the commented default's layout.

That ``show`` of each kind is a valid file of exactly the defaults, and every one-line mistake ``check`` reports, are
tested in tests/unit/bridge/core/test_config.py."""

from __future__ import annotations

import argparse
import math
import sys
from typing import Annotated, Literal

import pytest
from msgspec import Meta

from bridge.core.config import ConfigError, StationConfig
from bridge.core.wire import MissionSpec
from bridge.nodes.driver_config import driver_config_type
from bridge.tools import config_cmd
from bridge.tools.config_cmd import KIND_NAMES, _describe, _toml_value, check, kind_type, show

if sys.version_info >= (3, 11):
    import tomllib
else:  # the project's own fallback (bridge.core.config)
    import tomli as tomllib


def _back(text: str):
    return tomllib.loads(f"x = {text}\n")["x"]


def test_each_kind_names_its_struct() -> None:
    assert KIND_NAMES == ("driver", "mission", "station")
    assert kind_type("station") is StationConfig and kind_type("mission") is MissionSpec
    assert kind_type("driver") is driver_config_type()
    with pytest.raises(KeyError):
        kind_type("robot")


@pytest.mark.parametrize("value", [True, False, 0, -7, 2**40, 0.5, -1e-9, 1e300, "", "plain", 'a "quoted" \\ path',
                                   "tab\tand\nnewline", "del\x7f", "é ✓", [1, 2.5, "x"], (0.0, 1.0), [[1, 2], [3, 4]],
                                   {"a": 1, "b c": [True]}, [], {}])
def test_every_value_is_written_as_toml_that_reads_back_the_same(value) -> None:
    expected = list(value) if isinstance(value, tuple) else value
    got = _back(_toml_value(value))
    assert got == expected and type(got) is type(expected)


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_a_non_finite_number_is_written_as_tomls_own(value: float) -> None:
    got = _back(_toml_value(value))
    assert (math.isnan(got) and math.isnan(value)) or got == value


def test_a_value_without_a_toml_form_is_refused() -> None:
    with pytest.raises(TypeError, match="no TOML form for None"):
        _toml_value(None)
    with pytest.raises(TypeError, match="no TOML form"):
        _toml_value(object())


def test_a_keys_description_is_its_meaning_its_range_and_its_choices() -> None:
    assert _describe(Annotated[float, Meta(description="rate, Hz", ge=1.0, le=1000.0)]) == "rate, Hz; >= 1.0, <= 1000.0"
    assert _describe(Annotated[float, Meta(gt=0.0, lt=2.0)]) == "> 0.0, < 2.0"
    assert _describe(Annotated[float, Meta(ge=-1e9, le=1e9)]) == ""  # the "any number" guard is not a range
    assert _describe(Annotated[Literal["a", "b"], Meta(description="mode")]) == "mode; one of 'a', 'b'"
    assert _describe(Annotated[Annotated[int, Meta(description="inner")], Meta(ge=0)]) == "inner; >= 0"
    assert _describe(int) == ""


def test_the_commented_default_puts_tables_after_keys_each_with_its_comment() -> None:
    text = show("driver")
    lines = text.splitlines()
    assert lines[0].startswith("# scmbridge driver configuration: every key with its default")
    assert lines[1].startswith('robot = "learner"') and "# " in lines[1]
    i = lines.index("[driver]")
    assert lines[i + 1].startswith("# ") and any(ln.startswith("rate_hz = 50.0") and "Hz" in ln for ln in lines)
    assert "[driver.hard_limits]" in lines and "[link.udp]" in lines
    assert tomllib.loads(text)["driver"]["rate_hz"] == 50.0
    assert show("mission") == show("mission") and "path" in tomllib.loads(show("mission"))


def test_check_says_what_a_valid_file_is_guessing_its_kind_from_its_keys(tmp_path) -> None:
    m = tmp_path / "m.toml"
    m.write_text('name = "line"\npath = [[0.0, 0.0], [3.0, 4.0]]\nobstacles = [[1.0, 1.0, 0.2]]\n')
    assert check(str(m)) == f"{m}: a valid mission 'line': 2 waypoints, 5.00 m, 1 obstacles"
    d = tmp_path / "d.toml"
    d.write_text('robot = "rover1"\n[driver]\nrate_hz = 20\n')
    assert check(str(d)) == f"{d}: a valid driver configuration for robot 'rover1'"
    s = tmp_path / "s.toml"
    s.write_text('robot = "rover2"\n')
    assert check(str(s)) == f"{s}: a valid station configuration for robot 'rover2'"
    assert check(str(s), "driver") == f"{s}: a valid driver configuration for robot 'rover2'"  # named: not guessed


def test_check_of_the_wrong_kind_is_a_config_error(tmp_path) -> None:
    d = tmp_path / "d.toml"
    d.write_text("[driver]\nrate_hz = 20\n")
    with pytest.raises(ConfigError):
        check(str(d), "station")
    with pytest.raises(ConfigError, match="no such file"):
        check(str(tmp_path / "absent.toml"))


def test_run_check_and_run_show_print_one_answer(tmp_path, capsys) -> None:
    ap = argparse.ArgumentParser()
    config_cmd.arguments_check(ap)
    s = tmp_path / "s.toml"
    s.write_text("")
    assert config_cmd.run_check(ap.parse_args([str(s)])) == 0
    assert capsys.readouterr().out == f"{s}: a valid station configuration for robot 'learner'\n"
    ap = argparse.ArgumentParser()
    config_cmd.arguments_show(ap)
    assert config_cmd.run_show(ap.parse_args(["--kind", "station"])) == 0
    assert capsys.readouterr().out == show("station")
    with pytest.raises(SystemExit):
        ap.parse_args([])  # --kind is required


def test_check_runs_the_commands_own_checks_of_keys_and_missions(tmp_path) -> None:
    """Finding: ``config check`` passed files the commands refuse: a missing, short or world-readable key file, a
    missing mission; and an all-zero UDP key was accepted. It now runs the checks the driver and the station run
    when they start (drivers.udp.link_key, bridge.core.auth.load_key, load_mission_spec)."""
    import os

    from bridge.core.auth import KeyFileError, make_key
    from bridge.core.errors import UsageError
    from bridge.tools.config_cmd import check

    key = tmp_path / "udp.key"
    drv = tmp_path / "driver.toml"
    drv.write_text(f'robot = "r1"\n[link.udp]\nkey_file = "{key}"\n')
    with pytest.raises(KeyFileError, match="not found"):
        check(str(drv), "driver")
    make_key(key)
    assert "udp key checked" in check(str(drv), "driver")
    os.chmod(key, 0o644)
    with pytest.raises(KeyFileError, match="readable by others"):
        check(str(drv), "driver")
    key.write_text("00" * 32 + "\n")
    os.chmod(key, 0o600)
    with pytest.raises(KeyFileError, match="all-zero"):
        check(str(drv), "driver")
    key.write_text("ab" * 8 + "\n")
    with pytest.raises(KeyFileError, match="random bytes"):
        check(str(drv), "driver")
    no_key = tmp_path / "nokey.toml"  # (which link a robot uses is not in the file: a link without a key passes)
    no_key.write_text('robot = "r1"\n[link.udp]\nrobot_port = 47800\n')
    assert "checked" not in check(str(no_key), "driver")
    st = tmp_path / "station.toml"
    st.write_text(f'robot = "r1"\n[station]\nmission = "{tmp_path / "absent.toml"}"\n')
    with pytest.raises((ConfigError, UsageError), match="no such file"):
        check(str(st), "station")


def test_a_key_or_config_that_is_a_fifo_or_a_device_is_refused_without_blocking(tmp_path) -> None:
    """Finding: a FIFO where a key, a config or the store is read hung the reader; /dev/zero was read without
    bound. Each read checks a regular file of bounded size first (bridge.core.paths.read_bounded)."""
    import os

    from bridge.core.auth import KeyFileError, load_key
    from bridge.core.config import read_table
    from bridge.core.paths import NotAFile, read_bounded

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(NotAFile):
        read_bounded(fifo, 100)  # would block forever in open() or read() without the check
    with pytest.raises(KeyFileError):
        load_key(fifo)
    with pytest.raises(ConfigError, match="not a regular file"):
        read_table(fifo)
    zero = tmp_path / "zero.key"
    zero.symlink_to("/dev/zero")
    with pytest.raises(KeyFileError):
        load_key(zero)
    big = tmp_path / "big"
    big.write_bytes(b"x" * 200)
    with pytest.raises(NotAFile, match="larger than 100"):
        read_bounded(big, 100)
