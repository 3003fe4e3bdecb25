"""bridge/nodes/driver_cmd.py: the ``scmbridge driver`` command refuses what cannot work before any link or session
opens, each in one line (a usage error), and its ``--link`` offers the registered links."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

import drivers
from bridge.core.errors import UsageError
from bridge.nodes import driver_cmd


def _args(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    driver_cmd.arguments(ap)
    return ap.parse_args(list(argv))


def test_link_offers_every_registered_link() -> None:
    ap = argparse.ArgumentParser()
    driver_cmd.arguments(ap)
    (link,) = [a for a in ap._actions if "--link" in a.option_strings]
    assert set(link.choices) == set(drivers.LINKS)


@pytest.mark.parametrize(("argv", "said"), [
    (["--link", "udp", "--emulate"], "--emulate hosts CAN motor controllers"),
    (["--link", "can", "--drift", "battery"], "--drift changes the emulated controllers: give --emulate"),
    (["--link", "can", "--emulate", "--drift", "nonsense"], "nonsense"),
    (["--link", "can", "--insecure"], "--insecure is for --link udp"),
])
def test_what_cannot_work_is_one_line_before_anything_opens(argv: list[str], said: str) -> None:
    with pytest.raises(UsageError, match=said.replace("-", r"\-")):
        driver_cmd.run(_args(*argv))


def test_a_fence_on_a_link_without_one_is_refused(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="uploads ArduPilot's own fence"):
        driver_cmd.run(_args("--link", "can", "--fence", str(tmp_path / "fence.toml")))
