"""Typed configuration: every mistake a user can make in a station, driver or mission file is refused with exit
status 2 and one line naming the file, the key path and the problem, before anything opens; the commented default
`scmbridge config show` prints is itself a valid file holding exactly the defaults."""

from __future__ import annotations

import subprocess
import sys

import msgspec
import pytest

from bridge.core import config as C
from bridge.nodes.driver_config import load_driver
from bridge.tools import config_cmd

STATION_BAD = [
    ("[station]\nhorizn = 5\n", "station.horizn", "did you mean 'horizon'"),
    ('[station]\nrate_hz = "10"\n', "station.rate_hz", "expected a number, got text"),
    ("[station]\nrate_hz = -50\n", "station.rate_hz", ">= 0.5"),
    ("[station]\npersist_every_s = nan\n", "station.persist_every_s", "expected a finite number"),
    ("[station]\nmax_pose_age_s = inf\n", "station.max_pose_age_s", "expected a finite number"),
    ("[teacher_bounds]\nv = [0.6, 0.05]\nw = [-1, 1]\n", "teacher_bounds", "min must be < max"),
    ("[learner_bounds]\nv = [0.1]\nw = [-1, 1]\n", "learner_bounds.v", "length 2"),
    ('[transfer]\nmapper = "magic"\n', "transfer.mapper", "scm"),
    ('[transfer]\nlimits = "true"\n', "transfer.limits", "must be one of 'learned', 'teacher', got 'true'"),
    ("[transfer]\ngrid = [1, 11]\n", "transfer.grid[0]", ">= 2"),
    ('[teacher]\nkind = "oracle"\n', "teacher.kind", "external"),
    ("[calibration]\nreturn_radius_m = 3.0\nmax_distance_m = 2.0\n", "calibration", "must be below"),
    ('robot = "a/b"\n', "robot", "does not match"),
    ('robot = 5\n', "robot", "expected text"),
    ("[teacher_bounds]\nv = [0.05, true]\nw = [-1, 1]\n", "teacher_bounds.v[1]", "expected a number"),
    ("station = 3\n", "station", "expected a table"),
    ("[stations]\nrate_hz = 10\n", "stations", "did you mean 'station'"),
    # a dict's values and keys (these were msgspec tracebacks while the validator walked the types by hand)
    ('[fleet.shards]\nbase1 = ["a/b"]\n', "fleet.shards.base1[0]", "'a/b' does not match"),
    ('[fleet.shards]\n"a b" = ["r1"]\n', "fleet.shards", "key 'a b' does not match"),
    ("[fleet]\nshards = 3\n", "fleet.shards", "expected a table, got a whole number"),
    ("[fleet.shards]\nbase1 = []\n", "fleet", "serves no robot"),
]
DRIVER_BAD = [
    ("[driver]\ncmd_timout = 0.05\n", "driver.cmd_timout", "did you mean 'cmd_timeout'"),
    ("[driver.hard_limit]\nv = [0, 1]\nw = [-1, 1]\n", "driver.hard_limit", "did you mean 'hard_limits'"),
    ("[driver]\ncmd_timeout = nan\n", "driver.cmd_timeout", "expected a finite number"),
    ("[driver]\ncmd_timeout = inf\n", "driver.cmd_timeout", "expected a finite number"),
    ("[driver]\ncmd_timeout = 20\n", "driver.cmd_timeout", "must be <= 10.0, got 20"),
    ("[driver]\nrate_hz = 200\nmax_send_hz = 100\n", "driver", "below rate_hz"),
    ("[link.can]\nleft_nod = 5\n", "link.can.left_nod", "did you mean 'left_node'"),
    ("[link.can]\nwheel_radus = 0.1\n", "link.can.wheel_radus", "did you mean 'wheel_radius'"),
    ("[link.can]\nwheel_radius = nan\n", "link.can.wheel_radius", "expected a finite number"),
    ("[link.can]\nwheel_radius = -1\n", "link.can.wheel_radius", "must be > 0.0, got -1"),
    ("[link.can]\nleft_node = 1\nright_node = 1\n", "link.can", "each wheel needs its own node"),
    ("[link.can]\nleft_sign = 0.5\n", "link.can", "must be 1 or -1"),
    ("[link.udp]\nrobot_port = 70000\n", "link.udp.robot_port", "<= 65535"),
    ('[driver]\npose_source = "gps"\n', "driver.pose_source", "mocap"),
    # accepted before, and unsafe: an Estop with no source released the latch; a deadman that fires at once
    ('[driver]\nestop_release_sources = [""]\n', "driver.estop_release_sources[0]", "non-blank"),
    ('[driver]\nestop_release_sources = ["  "]\n', "driver.estop_release_sources[0]", "non-blank"),
    ("[driver]\nestop_release_sources = []\n", "driver.estop_release_sources", "at least 1"),
    ("[driver]\ncmd_timeout = 1e-300\n", "driver.cmd_timeout", ">= 0.02"),
    ("[driver.hard_limits]\nv = [-1e9, 1e9]\nw = [-1, 1]\n", "driver", "beyond any rover"),
    # a float whose type has no range is finite too (its rule would otherwise speak of nan)
    ("[link.can]\nleft_sign = nan\n", "link.can.left_sign", "expected a finite number, got nan"),
    ("[link.can]\ninitial_pose = [0, 0, 2e9]\n", "link.can.initial_pose[2]", "between -1e9 and 1e9"),
]
MISSION_BAD = [
    ('name = "m"\n', "path", "required key is missing"),
    ("path = [[0, 0], [0, 0]]\n", "", "the path has no length"),
    ("path = [[0, 0], [1, nan]]\n", "path[1][1]", "expected a finite number, got nan"),
    ("path = [[0, 0], [1, 0]]\nobstacles = [[1, 1]]\n", "obstacles[0]", "needs at least 3 (length 2)"),
    ('path = [[0, 0], [1, 0]]\nstart = "x"\n', "start", "expected a list, got text"),
    ('path = [[0, 0], [1, 0]]\nnam = "x"\n', "nam", "did you mean 'name'"),
]


@pytest.mark.parametrize(("text", "where", "problem"), STATION_BAD + DRIVER_BAD)
def test_every_mistake_is_one_line_naming_the_key(tmp_path, text: str, where: str, problem: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    kind = "driver" if (text.startswith(("[driver", "[link"))) else "station"
    with pytest.raises(C.ConfigError) as err:
        config_cmd.check(str(f), kind)
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"{f}: {where}"), line
    assert problem in line, line
    assert "`" not in line and "Expected" not in line, f"msgspec's own wording leaked: {line}"


@pytest.mark.parametrize(("text", "where", "problem"), MISSION_BAD)
def test_every_mistake_in_a_mission_file_is_one_line(tmp_path, text: str, where: str, problem: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(C.ConfigError) as err:
        config_cmd.check(str(f), "mission")
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"{f}: {where}: " if where else f"{f}: "), line
    assert problem in line and "`" not in line and "Expected" not in line, line


def test_missing_and_malformed_files_are_one_line_too(tmp_path) -> None:
    with pytest.raises(C.ConfigError, match="no such file"):
        C.load_station(tmp_path / "none.toml")
    bad = tmp_path / "broken.toml"
    bad.write_text("[station\nrate_hz = 1\n")
    with pytest.raises(C.ConfigError, match="not valid TOML"):
        load_driver(bad)


def test_text_that_is_not_utf8_or_nested_too_deeply_is_one_line(tmp_path) -> None:
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('robot = "r\xf6ver"\n'.encode("latin-1"))
    with pytest.raises(C.ConfigError, match="not UTF-8 text"):
        C.load_station(bad)
    deep = tmp_path / "deep.toml"
    deep.write_text("robot = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(C.ConfigError) as err:
        C.load_station(deep)
    assert "\n" not in str(err.value) and ("nested too deeply" in str(err.value) or "robot" in str(err.value))
    a_dir = tmp_path / "adir"
    a_dir.mkdir()
    with pytest.raises(C.ConfigError, match="is a directory"):
        load_driver(a_dir)


@pytest.mark.parametrize("kind", ["station", "driver", "mission"])
def test_the_commented_default_is_a_valid_file_of_exactly_the_defaults(tmp_path, kind: str) -> None:
    f = tmp_path / f"{kind}.toml"
    f.write_text(config_cmd.show(kind))
    got = C.load(f, config_cmd.kind_type(kind))
    if kind != "mission":
        assert got == msgspec.convert({}, config_cmd.kind_type(kind))


@pytest.mark.parametrize("command", [["driver", "--link", "can"], ["driver", "--link", "udp"], ["station"],
                                     ["calibrate"], ["config", "check"]])
def test_every_command_that_reads_a_config_refuses_a_typo_before_opening_anything(tmp_path, command) -> None:
    f = tmp_path / "typo.toml"
    f.write_text("[driver]\ncmd_timout = 0.05\n" if command[0] == "driver" else "[station]\nhorizn = 5\n")
    res = subprocess.run([sys.executable, "-m", "bridge", *command, *(["--config"] if command[0] != "config"
                                                                         else []), str(f)],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "unknown key (did you mean" in lines[0] and str(f) in lines[0], res.stderr
    assert "Traceback" not in res.stderr


def test_a_non_finite_start_pose_is_an_argument_error() -> None:
    res = subprocess.run([sys.executable, "-m", "bridge", "driver", "--link", "can", "--x0", "nan,0,0"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and "three finite numbers" in res.stderr and "Traceback" not in res.stderr


def test_a_malformed_or_missing_zenoh_config_is_one_line(tmp_path) -> None:
    bad = tmp_path / "bad.json5"
    bad.write_text("{ not json5")
    for path in (bad, tmp_path / "missing.json5"):
        res = subprocess.run([sys.executable, "-m", "bridge", "status", "--all", "--zenoh-config", str(path)],
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
        assert str(path) in res.stderr and "Traceback" not in res.stderr


def test_the_stations_fill_budget_default_is_the_guided_policys() -> None:
    # the config module stays free of the numerical stack (the robot side imports it), so it repeats the number
    from transfer.policy import FILL_BUDGET, GuidedPolicy

    assert C.TransferSection().fill_budget == FILL_BUDGET
    assert GuidedPolicy.__init__.__kwdefaults__["fill_budget"] == FILL_BUDGET


def test_the_stations_change_detection_defaults_are_the_stores() -> None:
    # repeated for the same reason: the store's own default change tolerance; the store adapts only when told to
    from transfer.store import CHANGE_TOL, PairStore

    assert C.TransferSection().change_tol == CHANGE_TOL
    assert PairStore.__init__.__kwdefaults__["adapt"] is False


@pytest.mark.parametrize(("adapt", "fresh", "reloaded"), [("reloaded", False, True), (True, True, True),
                                                          (False, False, False)])
def test_a_station_adapts_from_its_first_run_by_default(adapt, fresh: bool, reloaded: bool) -> None:
    """``[transfer] adapt``: true (the default) re-learns changed cells always, also while the station learns from
    no pairs; "reloaded" only those of a saved store the station starts on; false never. A typo is refused with the
    choices."""
    t = msgspec.convert({"adapt": adapt}, C.TransferSection)
    assert (t.adapts(reloaded=False), t.adapts(reloaded=True)) == (fresh, reloaded)
    assert C.TransferSection().adapt is True
    with pytest.raises(msgspec.ValidationError, match="adapt"):
        msgspec.convert({"adapt": "yes"}, C.TransferSection)


def test_the_stations_turn_probe_choices_and_default_are_the_policys() -> None:
    # repeated for the same reason: the policy's own choices, and its default (the paper's) unless configured
    import typing

    from transfer.policy import TURN_PROBES, PaperPolicy

    hint = typing.get_type_hints(C.TransferSection, include_extras=True)["turn_probe"]
    assert typing.get_args(typing.get_args(hint)[0]) == TURN_PROBES
    assert C.TransferSection().turn_probe == PaperPolicy.__init__.__kwdefaults__["turn_probe"] == TURN_PROBES[0]


def test_the_teacher_is_bounded_by_the_learned_limits_unless_a_station_says_the_paper_baseline() -> None:
    # [transfer] limits: learned by default (the method); teacher, with identity and no exploration, the paper's
    # baseline learner (bridge.nodes.sources.SourceContext.box)
    assert C.TransferSection().limits == "learned"
    base = C.decode_toml('[transfer]\nmapper = "identity"\nexploration = "off"\nlimits = "teacher"\n',
                         C.StationConfig)
    assert (base.transfer.mapper, base.transfer.exploration, base.transfer.limits) == ("identity", "off", "teacher")
