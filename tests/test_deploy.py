"""What deploy/ ships must load: every Zenoh config, the example station and driver configurations."""

from __future__ import annotations

from pathlib import Path

import pytest
import zenoh

from bridge.config import load_driver, load_station
from drivers import open_driver

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"


@pytest.mark.parametrize("path", sorted((DEPLOY / "zenoh").glob("*.json5")), ids=lambda p: p.name)
def test_zenoh_configs_parse(path: Path) -> None:
    zenoh.Config.from_file(str(path))


def test_no_shipped_config_listens_on_every_interface_or_scouts_by_multicast() -> None:
    for path in (DEPLOY / "zenoh").glob("*.json5"):
        text = path.read_text()
        assert "0.0.0.0" not in text and "[::]" not in text, path
        assert "multicast: { enabled: false }" in text, path


def test_example_station_and_driver_configs_are_consistent() -> None:
    st = load_station(DEPLOY / "station.example.toml")
    tb, lb = st.teacher_bounds.bounds(), st.learner_bounds.bounds()
    assert tb.contains(lb.lo) and tb.contains(lb.hi)  # the learner is less capable than the teacher
    dr = load_driver(DEPLOY / "driver.example.toml")
    assert dr.robot == st.robot and dr.driver.cmd_timeout == pytest.approx(0.3)
    drv = open_driver("can", dr.link.can)  # constructing does no I/O
    assert drv.channel == "can0" and drv.interface == "socketcan"


def test_systemd_units_run_the_installed_commands() -> None:
    for unit in (DEPLOY / "systemd").glob("*.service"):
        text = unit.read_text()
        assert "ExecStart=/opt/scmbridge/.venv/bin/scmbridge " in text and "Restart=on-failure" in text


def test_an_unknown_link_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="unknown link"):
        open_driver("carrier-pigeon")


@pytest.mark.parametrize("link", ["udp", "mavlink"])
def test_example_link_configs_construct_their_drivers(link: str) -> None:
    cfg = load_driver(DEPLOY / f"driver.{link}.example.toml")
    drv = open_driver(link, getattr(cfg.link, link))
    assert drv.name == link and cfg.driver.cmd_timeout == pytest.approx(0.3)
