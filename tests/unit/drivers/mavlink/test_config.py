"""drivers/mavlink/config.py: ``[link.mavlink]`` (defaults, ranges, the position-timeout rule, whether it
authenticates). The link built from it is tested in tests/unit/drivers/mavlink/test_driver.py and test_signing.py."""

from __future__ import annotations

import subprocess
import sys

import pytest

from bridge.core.config import ConfigError, Rule, decode_toml
from drivers.mavlink.config import MavlinkLinkConfig


def test_the_defaults_are_a_ground_station_talking_to_vehicle_1() -> None:
    c = MavlinkLinkConfig()
    assert (c.url, c.target_system, c.target_component, c.source_system) == ("udpout:127.0.0.1:14550", 1, 1, 255)
    assert c.disarm_on_close and c.signing_key_file == ""
    assert c.position_timeout >= 2.0 / c.rate_hz  # the defaults obey their own rule


def test_reading_it_imports_no_pymavlink() -> None:
    code = ("import sys; from drivers.mavlink.config import MavlinkLinkConfig; MavlinkLinkConfig(); "
            "assert 'pymavlink' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_unsigned_links_say_so_and_signed_ones_say_nothing() -> None:
    assert MavlinkLinkConfig().unauthenticated() == "MAVLink signing is off (no signing_key_file)"
    assert MavlinkLinkConfig(signing_key_file="/etc/scmbridge/mavlink.key").unauthenticated() == ""


def test_a_position_timeout_shorter_than_two_periods_is_refused() -> None:
    with pytest.raises(Rule, match=r"position_timeout = 0.1 s is shorter than two LOCAL_POSITION_NED periods at "
                                   r"rate_hz = 10.0"):
        MavlinkLinkConfig(rate_hz=10.0, position_timeout=0.1)
    assert MavlinkLinkConfig(rate_hz=10.0, position_timeout=0.2).position_timeout == 0.2  # exactly two: accepted


@pytest.mark.parametrize(("text", "where"), [
    ('url = ""', "url"),
    ("target_system = 0", "target_system"),
    ("source_system = 256", "source_system"),
    ("rate_hz = 0.0", "rate_hz"),
    ("heartbeat_timeout = 1.0", "heartbeat_timeout"),  # under 1.5 HEARTBEAT periods
    ("command_retries = 11", "command_retries"),
    ("reconnect_max_s = 0.1", "reconnect_max_s"),
    ("rate_hz = inf", "rate_hz"),
    ("rate_hz = 1.0", "position_timeout"),  # the default 1 s is one period at 1 Hz
    ("ack_timout = 1.0", "ack_timeout"),  # the nearest valid name is suggested
])
def test_a_bad_value_in_toml_is_one_line_naming_the_key(text: str, where: str) -> None:
    with pytest.raises(ConfigError) as err:
        decode_toml(text, MavlinkLinkConfig, "driver.toml")
    msg = str(err.value)
    assert msg.startswith("driver.toml: ") and where in msg and "\n" not in msg
