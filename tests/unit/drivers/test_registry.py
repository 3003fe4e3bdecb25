"""A link is a plugin: one module (its config struct, its driver, ``EMULATED``) plus its name in ``drivers.LINKS``
(an entry point of the ``scmbridge.links`` group does that for an installed package: test_link_plugins.py).

A loopback link written here, outside the repository, and registered by that one line only, gets its ``[link.<name>]``
section in the driver host's configuration (with the usual one-line errors), is built by ``open_driver``, and is
offered by the driver host's ``--link``; and reading a configuration imports no vehicle library."""

from __future__ import annotations

import argparse
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

import drivers
from bridge.core.config import ConfigError
from bridge.nodes import driver_cmd
from bridge.nodes.driver_config import DriverConfig, load_driver
from bridge.tools import config_cmd
from drivers.base import Driver

MODULE = "scm_test_loopback_link"

LOOPBACK = textwrap.dedent('''
    """A loopback link: the vehicle is a point that moves exactly as commanded."""

    from __future__ import annotations

    import math
    from typing import Annotated

    from bridge.core.config import Cfg, Rule, meta
    from drivers.base import FailsafeReport, LinkHealth, Pose


    class LoopbackLinkConfig(Cfg):
        """``[link.loopback]``: a point vehicle that moves exactly as commanded."""

        gain: Annotated[float, meta("how much of each command the point executes", gt=0.0, le=10.0)] = 1.0
        start_x: Annotated[float, meta("x at open, m", ge=-100.0, le=100.0)] = 0.0

        def __post_init__(self) -> None:
            if self.gain == 3.0:
                raise Rule("gain = 3.0 is unlucky")


    class LoopbackDriver:
        name = "loopback"

        def __init__(self, config: LoopbackLinkConfig) -> None:
            self.config = config
            self.pose = (config.start_x, 0.0, 0.0)
            self.cmd = (0.0, 0.0)
            self.last: float | None = None
            self.opened = self.engaged = False
            self.sent = self.received = 0

        def open(self, now: float) -> None:
            self.opened, self.last = True, now

        def engage(self, now: float, clear_faults: bool = False) -> None:
            self.engaged = True

        def failsafe(self) -> FailsafeReport:
            return FailsafeReport(drive_on_s=0.0, text="a loopback stops with its host")

        def send(self, v: float, omega: float, now: float) -> None:
            self.cmd = (self.config.gain * v, self.config.gain * omega)
            self.sent += 1

        def stop(self, now: float) -> None:
            self.cmd = (0.0, 0.0)

        def poll(self, now: float) -> list[Pose]:
            if not self.opened or self.last is None:
                return []
            dt, self.last = now - self.last, now
            x, y, th = self.pose
            v, w = self.cmd
            self.pose = (x + v * dt * math.cos(th), y + v * dt * math.sin(th), th + w * dt)
            self.received += 1
            return [Pose(now, *self.pose, v, w)]

        def health(self, now: float) -> LinkHealth:
            return LinkHealth(connected=self.opened, ok=self.opened and self.engaged,
                              text="ready" if self.engaged else "not engaged", frames_sent=self.sent,
                              frames_received=self.received)

        def clear_faults(self, now: float) -> None:
            pass

        def close(self, disarm: bool = True, stop_speed: float = 0.05, stop_timeout: float = 3.0,
                  now: float | None = None) -> None:
            self.opened = False


    CONFIG = LoopbackLinkConfig
    DRIVER = LoopbackDriver
    EMULATED = False
''')


@pytest.fixture
def loopback(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """The loopback module on the path and its one registry line; the module is forgotten afterwards."""
    (tmp_path / f"{MODULE}.py").write_text(LOOPBACK)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(drivers.LINKS, "loopback", MODULE)
    yield "loopback"
    sys.modules.pop(MODULE, None)


def test_a_driver_toml_decodes_its_section_into_the_new_links_config(tmp_path: Path, loopback: str) -> None:
    f = tmp_path / "driver.toml"
    f.write_text('robot = "pt"\n[link.loopback]\ngain = 0.5\nstart_x = 2.0\n[link.can]\nleft_node = 3\n')
    cfg = load_driver(f)
    assert isinstance(cfg, DriverConfig) and cfg.robot == "pt"
    section = cfg.link.loopback
    assert type(section) is drivers.link_config(loopback) and type(section).__name__ == "LoopbackLinkConfig"
    assert (section.gain, section.start_x) == (0.5, 2.0)
    assert cfg.link.can.left_node == 3  # the registered links keep their sections
    assert load_driver(None).link.loopback == drivers.link_config(loopback)()
    assert "[link.loopback]" in config_cmd.show("driver") and "how much of each command" in config_cmd.show("driver")


@pytest.mark.parametrize(("text", "problem"), [
    ("[link.loopback]\ngian = 1.0\n", "driver.toml: link.loopback.gian: unknown key (did you mean 'gain'?)"),
    ("[link.loopback]\ngain = 20\n", "driver.toml: link.loopback.gain: must be <= 10.0, got 20"),
    ("[link.loopback]\ngain = nan\n", "driver.toml: link.loopback.gain: expected a finite number, got nan"),
    ("[link.loopback]\ngain = 3.0\n", "driver.toml: link.loopback: gain = 3.0 is unlucky"),
    ("[link.loopbak]\ngain = 1.0\n", "driver.toml: link.loopbak: unknown key (did you mean 'loopback'?)"),
])
def test_the_new_links_mistakes_are_the_usual_one_line(tmp_path: Path, loopback: str, text: str, problem: str) -> None:
    f = tmp_path / "driver.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_driver(f)
    assert str(err.value) == f"{tmp_path}/{problem}"


def test_open_driver_builds_the_new_link_and_it_drives(loopback: str) -> None:
    driver = drivers.open_driver(loopback, drivers.link_config(loopback)(gain=2.0))
    assert isinstance(driver, Driver) and driver.name == loopback
    driver.open(10.0)
    driver.engage(10.0)
    assert driver.health(10.0).ok
    driver.send(0.5, 0.0, 10.0)
    (pose,) = driver.poll(11.0)
    assert (pose.x, pose.v) == (pytest.approx(1.0), pytest.approx(1.0))  # gain 2 x 0.5 m/s for 1 s
    assert drivers.open_driver(loopback).config.gain == 1.0  # no config: the link's defaults


def test_the_driver_hosts_link_option_offers_the_new_link(loopback: str) -> None:
    ap = argparse.ArgumentParser()
    driver_cmd.arguments(ap)
    (link,) = [a for a in ap._actions if "--link" in a.option_strings]
    assert loopback in link.choices and set(link.choices) == set(drivers.LINKS)
    assert ap.parse_args(["--link", loopback]).link == loopback


def test_a_name_not_registered_is_refused_with_the_known_ones() -> None:
    with pytest.raises(ValueError, match="unknown link 'canbus'; known links: can, mavlink, udp"):
        drivers.open_driver("canbus")


def test_reading_a_driver_configuration_imports_no_vehicle_library() -> None:
    """python-can, cantools and pymavlink load when a driver is built, not with the configuration's link sections."""
    code = ("import sys\nfrom bridge.nodes.driver_config import load_driver\nload_driver(None)\n"
            "print(sorted(m for m in ('can', 'cantools', 'pymavlink') if m in sys.modules))\n"
            "import drivers\ndrivers.open_driver('mavlink')\nprint('pymavlink' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[3])
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["[]", "True"]
