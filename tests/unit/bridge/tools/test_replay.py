"""bridge/tools/replay.py: the ``--robot-rename A=B`` argument and the command's refusals before a session opens.
Replaying a recording over a real router (order, pace, renames, commands only with --with-commands) is in
tests/integration/test_record.py; the renaming of keys and messages in tests/unit/bridge/tools/test_mcap_format.py."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from bridge.core.errors import UsageError
from bridge.tools import replay


def test_a_rename_is_two_robot_names() -> None:
    assert replay._rename_arg("rover1=sim-2") == ("rover1", "sim-2")


@pytest.mark.parametrize(("text", "says"), [
    ("rover1", "expected A=B"),
    ("rover1=", "robot name ''"),
    ("=rover2", "robot name ''"),
    ("a/b=c", "robot name 'a/b'"),
    ("a=b=c", "robot name 'b=c'"),
    ("a=*", "robot name '*'"),
])
def test_a_bad_rename_names_itself_and_the_problem(text: str, says: str) -> None:
    pattern = re.escape(f"--robot-rename '{text}': ") + ".*" + re.escape(says)
    with pytest.raises(argparse.ArgumentTypeError, match=pattern):
        replay._rename_arg(text)


def test_the_parser_collects_renames_and_keeps_commands_off_by_default() -> None:
    ap = argparse.ArgumentParser()
    replay.arguments(ap)
    args = ap.parse_args(["a.mcap", "b.mcap", "--robot-rename", "r1=r9", "--robot-rename", "r2=r8", "--fast"])
    assert args.files == ["a.mcap", "b.mcap"] and dict(args.robot_rename) == {"r1": "r9", "r2": "r8"}
    assert args.fast and not args.with_commands and args.wait == 5.0
    with pytest.raises(SystemExit):
        ap.parse_args(["a.mcap", "--fast", "--speed", "2"])  # one pace or the other


def test_a_missing_file_is_refused_before_anything_is_published(tmp_path: Path) -> None:
    ap = argparse.ArgumentParser()
    replay.arguments(ap)
    with pytest.raises(UsageError, match=r"missing\.mcap: no such file"):
        replay.run(ap.parse_args([str(tmp_path / "missing.mcap")]))
