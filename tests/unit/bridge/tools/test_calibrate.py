"""bridge/tools/calibrate.py: ``scmbridge calibrate``'s own argument (``--grid NVxNW``) and its refusals before it
commands anything: overrides that break the ``[calibration]`` rules, and an identity the lab's access control would
deny (it would never move the robot). The plan itself is tested in tests/unit/transfer/test_calibration.py, the
command end to end over Zenoh in tests/integration/test_calibrate.py."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import pytest

from bridge.core.config import ConfigError
from bridge.core.errors import Denied
from bridge.tools import calibrate, deploy
from bridge.tools.calibrate import grid_arg


@pytest.mark.parametrize(("text", "grid"), [("5x5", (5, 5)), ("3X7", (3, 7)), ("2x21", (2, 21)), ("21x2", (21, 2))])
def test_a_grid_is_commands_per_axis(text: str, grid: tuple[int, int]) -> None:
    assert grid_arg(text) == grid


@pytest.mark.parametrize(("text", "says"), [
    ("5", "is not NVxNW"), ("5x", "is not NVxNW"), ("axb", "is not NVxNW"), ("5x5x5", "is not NVxNW"),
    ("1x5", "each axis needs 2 to 21 commands"), ("5x22", "each axis needs 2 to 21 commands"),
    ("-3x5", "each axis needs 2 to 21"),
])
def test_a_grid_that_is_not_two_to_21_per_axis_is_refused(text: str, says: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=says):
        grid_arg(text)


def _args(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    calibrate.arguments(ap)
    return ap.parse_args(list(argv))


def test_the_parser_leaves_the_configuration_in_charge_unless_told() -> None:
    a = _args()
    assert (a.grid, a.hold, a.max_distance, a.duration, a.robot, a.store) == (None,) * 6
    assert _args("--grid", "3x4", "--hold", "0.5").grid == (3, 4)
    with pytest.raises(SystemExit):
        _args("--grid", "1x1")


def test_an_override_outside_the_calibration_range_is_a_config_error_naming_the_command_line(tmp_path) -> None:
    with pytest.raises(ConfigError) as err:
        calibrate.run(_args("--hold", "120", "--store", str(tmp_path / "pairs.bin")))
    assert str(err.value).startswith("command line: calibration: ") and "\n" not in str(err.value)
    assert not (tmp_path / "pairs.bin").exists()  # nothing ran


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
def test_an_identity_the_labs_rules_deny_is_refused_before_any_session(certs, tmp_path: Path) -> None:
    conf = tmp_path / "operator.json5"
    # the operator's certificate: the lab's rules let only the station publish cmd
    conf.write_text(json.dumps(deploy.client_config("operator", connect="tls/127.0.0.1:9", certs=certs.lab)))
    with pytest.raises(Denied) as err:
        calibrate.run(_args("--robot", "rover1", "--zenoh-config", str(conf), "--store", str(tmp_path / "p.bin"),
                            "--max-distance", "1.0"))
    text = str(err.value)
    assert "denied: identity 'operator'" in text and "scm/rover1/cmd" in text and "station-client.json5" in text
