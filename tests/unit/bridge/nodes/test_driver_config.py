"""The driver host's configuration (:mod:`bridge.nodes.driver_config`): the documented defaults, the cross-field
rules at their edges, and a ``[link.<name>]`` section per link built from the links' own structs.

Each one-line mistake in a driver file (a typo, a range, a rule) is tested in tests/unit/bridge/core/test_config.py;
a link added to the registry getting its section, in tests/unit/drivers/test_registry.py."""

from __future__ import annotations

import msgspec
import pytest

import drivers
from bridge.core.config import BoundsConfig, Cfg, ConfigError, Rule
from bridge.nodes.driver_config import (
    DEFAULT_HARD_LIMITS,
    HARD_V_MAX,
    HARD_W_MAX,
    DriverConfig,
    DriverSection,
    LinkSection,
    driver_config_type,
    link_section,
    load_driver,
)


def test_the_defaults_are_the_safe_documented_ones() -> None:
    cfg = load_driver(None)
    d = cfg.driver
    assert cfg.robot == "learner" and isinstance(cfg, DriverConfig)
    assert (d.rate_hz, d.cmd_timeout, d.max_send_hz, d.max_telemetry_age_s) == (50.0, 0.3, 100.0, 0.5)
    assert d.hard_limits == DEFAULT_HARD_LIMITS and (d.hard_limits.v, d.hard_limits.w) == ((-0.5, 0.5), (-1.0, 1.0))
    assert d.estop_release_sources == ("operator",)
    assert d.pose_source == "link" and not d.engage_on_start  # a person engages, also after a restart
    for name in drivers.LINKS:  # every registered link has its section, at that link's own defaults
        assert getattr(cfg.link, name) == drivers.link_config(name)()


def test_max_send_hz_may_equal_rate_hz_but_not_be_below_it() -> None:
    assert DriverSection(rate_hz=100.0, max_send_hz=100.0).max_send_hz == 100.0
    with pytest.raises(Rule, match="max_send_hz = 99.0 is below rate_hz = 100.0: every tick sends"):
        DriverSection(rate_hz=100.0, max_send_hz=99.0)


@pytest.mark.parametrize(("v", "w", "ok"), [
    ((-HARD_V_MAX, HARD_V_MAX), (-HARD_W_MAX, HARD_W_MAX), True),  # the edge itself is a vehicle
    ((0.0, HARD_V_MAX + 0.1), (-1.0, 1.0), False),
    ((-HARD_V_MAX - 0.1, 0.0), (-1.0, 1.0), False),
    ((-1.0, 1.0), (-HARD_W_MAX - 1.0, 1.0), False),
    ((-1.0, 1.0), (-1.0, HARD_W_MAX + 1.0), False),
])
def test_hard_limits_beyond_any_rover_are_a_typo(v, w, ok: bool) -> None:
    box = BoundsConfig(v=v, w=w)
    if ok:
        assert DriverSection(hard_limits=box).hard_limits == box
    else:
        with pytest.raises(Rule, match="beyond any rover this drives"):
            DriverSection(hard_limits=box)


def test_a_file_sets_the_driver_and_one_links_section_and_leaves_the_others_default(tmp_path) -> None:
    f = tmp_path / "driver.toml"
    f.write_text('robot = "rover1"\n[driver]\nrate_hz = 20\nmax_send_hz = 40\npose_source = "mocap"\n'
                 'estop_release_sources = ["operator", "safety"]\n'
                 '[link.udp]\nrobot_host = "127.0.0.2"\nrobot_port = 9000\n')
    cfg = load_driver(f)
    assert cfg.robot == "rover1" and cfg.driver.rate_hz == 20.0 and cfg.driver.pose_source == "mocap"
    assert cfg.driver.estop_release_sources == ("operator", "safety")
    assert (cfg.link.udp.robot_host, cfg.link.udp.robot_port) == ("127.0.0.2", 9000)
    assert cfg.link.can == drivers.link_config("can")()  # untouched sections keep their link's defaults
    assert load_driver(str(f)) == cfg  # a str path too


def test_a_section_for_an_unknown_link_is_refused_naming_it(tmp_path) -> None:
    f = tmp_path / "driver.toml"
    f.write_text("[link.serial]\nport = 1\n")
    with pytest.raises(ConfigError, match=r"link\.serial"):
        load_driver(f)


def test_link_section_builds_one_optional_table_per_link_from_its_own_struct() -> None:
    class Alpha(Cfg):
        gain: float = 1.5

    class Beta(Cfg):
        port: int = 7

    section = link_section((("alpha", Alpha), ("beta", Beta)))
    assert issubclass(section, Cfg) and section.__struct_fields__ == ("alpha", "beta")
    assert section() == section(alpha=Alpha(), beta=Beta())  # each defaults to its link's own defaults
    got = msgspec.convert({"beta": {"port": 9}}, section)
    assert got.alpha == Alpha() and got.beta == Beta(port=9)
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"beta": {"port": "nine"}}, section)


def test_the_config_type_is_driver_config_itself_for_the_links_registered_at_import() -> None:
    assert driver_config_type() is DriverConfig  # nothing registered since: no new class each call
    assert set(LinkSection.__struct_fields__) == set(drivers.LINKS)
