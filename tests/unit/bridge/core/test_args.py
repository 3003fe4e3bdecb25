"""The argument types every command shares (:mod:`bridge.core.args`): what each accepts, what it refuses and the
line argparse prints for it. (tests/repo/test_cli.py checks that the parsers use them.)"""

from __future__ import annotations

import argparse

import pytest

from bridge.core.args import pose_arg, positive_float, robot_arg, robots_arg


def test_a_pose_is_three_finite_numbers() -> None:
    assert pose_arg("1,-2.5,0.3") == (1.0, -2.5, 0.3)
    assert pose_arg(" 0 , 1e-3 ,-3.14") == (0.0, 1e-3, -3.14)  # float() takes surrounding blanks
    assert isinstance(pose_arg("0,0,0"), tuple)


@pytest.mark.parametrize(("text", "says"), [
    ("1,2", "three finite numbers"),
    ("1,2,3,4", "three finite numbers"),
    ("1,nan,0", "three finite numbers"),
    ("inf,0,0", "three finite numbers"),
    ("a,b,c", "(three numbers)"),
    ("", "(three numbers)"),
    ("1;2;3", "(three numbers)"),
])
def test_a_pose_that_is_not_three_finite_numbers_is_refused_naming_what_was_given(text: str, says: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError) as err:
        pose_arg(text)
    assert repr(text) in str(err.value) and says in str(err.value)


def test_a_positive_float_is_finite_and_above_zero() -> None:
    assert positive_float("0.5") == 0.5 and positive_float("1e3") == 1000.0
    for text in ("0", "-1", "nan", "inf", "-inf"):
        with pytest.raises(argparse.ArgumentTypeError, match="must be a finite number > 0"):
            positive_float(text)
    with pytest.raises(argparse.ArgumentTypeError, match="'fast' is not a number"):
        positive_float("fast")


def test_a_robot_name_is_one_key_chunk() -> None:
    assert robot_arg("rover_1-B") == "rover_1-B"
    assert robot_arg("x" * 64) == "x" * 64
    for bad in ("", "a/b", "a*", "r 1", "x" * 65, "rö", "$r", "a?b", "a#b"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"must be 1-64 characters of \[A-Za-z0-9_-\]"):
            robot_arg(bad)


def test_robot_names_are_comma_separated_without_blanks_or_repeats() -> None:
    assert robots_arg("r1") == ["r1"]
    assert robots_arg(" r1 ,r2,, r3 ") == ["r1", "r2", "r3"]  # blanks around names and empty items are dropped
    with pytest.raises(argparse.ArgumentTypeError, match="give at least one robot name"):
        robots_arg(" , ,")
    with pytest.raises(argparse.ArgumentTypeError, match="names a robot twice"):
        robots_arg("r1,r2, r1")
    with pytest.raises(argparse.ArgumentTypeError, match="must be 1-64 characters"):
        robots_arg("r1,r/2")


def test_a_mistake_is_one_argparse_line_and_exit_status_2(capsys) -> None:
    ap = argparse.ArgumentParser(prog="t")
    ap.add_argument("--x0", type=pose_arg)
    ap.add_argument("--rate", type=positive_float)
    assert ap.parse_args(["--x0", "1,2,3", "--rate", "2"]).x0 == (1.0, 2.0, 3.0)
    with pytest.raises(SystemExit) as exit_:
        ap.parse_args(["--rate", "-2"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "argument --rate: '-2' must be a finite number > 0" in err and "Traceback" not in err
