"""drivers/can/config.py: ``[link.can]`` (defaults, ranges and cross-field rules, each refused with a one-line
:class:`ConfigError` naming the key when read from TOML). The backoff rule alone is also in
tests/unit/drivers/can/test_driver.py."""

from __future__ import annotations

import subprocess
import sys

import pytest

from bridge.core.config import ConfigError, Rule, decode_toml
from drivers.can.config import CanLinkConfig


def test_the_defaults_are_a_two_wheel_socketcan_base() -> None:
    c = CanLinkConfig()
    assert (c.interface, c.channel, c.bitrate, c.fd) == ("socketcan", "can0", 500_000, False)
    assert (c.left_node, c.right_node, c.left_sign, c.right_sign) == (0, 1, 1.0, -1.0)
    assert c.initial_pose == (0.0, 0.0, 0.0) and c.reopen_backoff <= c.reopen_backoff_max


def test_reading_it_imports_no_can_library() -> None:
    code = ("import sys; from drivers.can.config import CanLinkConfig; CanLinkConfig(); "
            "assert 'can' not in sys.modules and 'cantools' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_both_wheels_on_one_node_are_refused() -> None:
    with pytest.raises(Rule, match="left_node and right_node are both 3"):
        CanLinkConfig(left_node=3, right_node=3)


@pytest.mark.parametrize("key", ["left_sign", "right_sign"])
@pytest.mark.parametrize("value", [0.0, 2.0, -0.5])
def test_a_wheel_sign_is_one_or_minus_one(key: str, value: float) -> None:
    with pytest.raises(Rule, match=f"{key} = {value}: must be 1 or -1"):
        CanLinkConfig(**{key: value})


def test_an_integer_sign_in_toml_is_accepted() -> None:
    c = decode_toml("left_sign = -1\nright_sign = 1\n", CanLinkConfig)
    assert (c.left_sign, c.right_sign) == (-1.0, 1.0)


@pytest.mark.parametrize(("text", "where"), [
    ("left_node = 64", "left_node"),
    ("wheel_radius = 0.0", "wheel_radius"),
    ("track_width = -1.0", "track_width"),
    ("bitrate = 5000", "bitrate"),
    ("heartbeat_timeout = 0.01", "heartbeat_timeout"),
    ('channel = ""', "channel"),
    ("initial_pose = [0.0, nan, 0.0]", "initial_pose"),
    ("left_node = 2\nright_node = 2", "left_node"),
    ("reopen_backoff = 1.0\nreopen_backoff_max = 0.5", "reopen_backoff_max"),
    ("heartbeat_timout = 0.5", "heartbeat_timeout"),  # the nearest valid name is suggested
])
def test_a_bad_value_in_toml_is_one_line_naming_the_key(text: str, where: str) -> None:
    with pytest.raises(ConfigError) as err:
        decode_toml(text, CanLinkConfig, "driver.toml")
    msg = str(err.value)
    assert msg.startswith("driver.toml: ") and where in msg and "\n" not in msg
