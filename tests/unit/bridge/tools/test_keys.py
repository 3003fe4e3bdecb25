"""``scmbridge keys udp|mavlink`` (:mod:`bridge.tools.keys`): a key made in the state directory under the robot's
and the link's name (or ``--out``), its path printed, private, and an existing key kept unless ``--force``. (The key
file's own rules, readable by others or malformed, are tested in tests/unit/bridge/core/test_auth.py.)"""

from __future__ import annotations

import argparse

import pytest

from bridge.core.auth import KeyFileError, load_key
from bridge.core.paths import state_dir
from bridge.tools import keys


def _args(link: str, *argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    getattr(keys, f"arguments_{link}")(ap)
    return ap.parse_args(list(argv))


@pytest.mark.parametrize("link", ["udp", "mavlink"])
def test_a_key_is_made_in_the_state_directory_and_its_path_printed(link: str, capsys) -> None:
    run = getattr(keys, f"run_{link}")
    assert run(_args(link, "--robot", "rover1")) == 0
    path = state_dir() / "keys" / f"rover1-{link}.key"
    assert capsys.readouterr().out == f"{path}\n"
    assert path.stat().st_mode & 0o777 == 0o600 and len(load_key(path, link)) == 32


def test_an_existing_key_is_kept_unless_forced(tmp_path, capsys) -> None:
    out = tmp_path / "k" / "robot.key"
    assert keys.run_udp(_args("udp", "--robot", "r1", "--out", str(out))) == 0
    first = out.read_bytes()
    with pytest.raises(KeyFileError, match="exists .*give --force to replace it"):
        keys.run_udp(_args("udp", "--robot", "r1", "--out", str(out)))
    assert out.read_bytes() == first  # every robot using it keeps answering
    assert keys.run_udp(_args("udp", "--robot", "r1", "--out", str(out), "--force")) == 0
    assert out.read_bytes() != first
    assert capsys.readouterr().out.splitlines() == [str(out), str(out)]


def test_the_robot_is_required_and_must_be_a_robot_name(capsys) -> None:
    for argv in ([], ["--robot", "a/b"]):
        with pytest.raises(SystemExit) as exit_:
            _args("mavlink", *argv)
        assert exit_.value.code == 2
    assert "a/b" in capsys.readouterr().err
