"""sim_learner/runs.py: what the paper's simulations share (the interval, the progress bar, a run and its
deviation). ``mean_dev_last_half`` on a real MPC run is also used in tests/unit/transfer/teacher/test_mpc.py."""

from __future__ import annotations

import io

import numpy as np
import pytest

from sim_learner.runs import DT, Progress, Run, deviation_profile, mean_dev_last_half
from transfer.mission import Mission
from transfer.teacher.path import Polyline

LINE = Mission("line", Polyline(np.array([[0.0, 0.0], [10.0, 0.0]])), np.zeros((0, 3)), 0.2)


def test_the_control_interval_is_the_papers() -> None:
    assert DT == 0.1


def test_run_arrays_and_method_counts() -> None:
    r = Run("scm")
    a = r.arrays()
    assert set(a) == {"scm_poses", "scm_commands", "scm_teacher"}
    assert a["scm_commands"].shape == (0, 2) and a["scm_teacher"].shape == (0, 2)  # an empty run still has columns
    assert r.method_counts() == {"scm": 0, "direct": 0, "perturb": 0}
    r.poses += [np.zeros(3), np.ones(3)]
    r.commands += [np.array([0.1, 0.0]), np.array([0.2, 0.1])]
    r.methods += ["scm", "barycentric", "scm", "perturb"]
    a = r.arrays()
    assert a["scm_poses"].shape == (2, 3) and a["scm_commands"].tolist() == [[0.1, 0.0], [0.2, 0.1]]
    assert r.method_counts() == {"scm": 2, "direct": 0, "perturb": 1, "barycentric": 1}
    assert Run("x").poses is not Run("y").poses  # no shared default lists


def test_deviation_profile_and_the_last_half() -> None:
    poses = [np.array([x, y, 0.0]) for x, y in ((0.0, 0.5), (4.0, -0.2), (6.0, 0.1), (9.0, 0.3))]
    prog, dev = deviation_profile(poses, LINE)
    np.testing.assert_allclose(prog, [0.0, 0.4, 0.6, 0.9])
    np.testing.assert_allclose(dev, [0.5, 0.2, 0.1, 0.3])
    r = Run("scm", poses=poses)
    assert mean_dev_last_half(r, LINE) == pytest.approx(0.2)  # the poses at progress >= 0.5: 0.1 and 0.3
    assert mean_dev_last_half(Run("short", poses=poses[:2]), LINE) is None  # never got halfway


def test_progress_is_silent_off_a_terminal_and_draws_a_bar_on_one(monkeypatch, capsys) -> None:
    p = Progress("mpc")
    p(0.5, "half")
    p.done()
    assert capsys.readouterr().err == ""

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty = Tty()
    monkeypatch.setattr("sys.stderr", tty)
    p = Progress("mpc")
    p(0.5, "half")
    p(2.0)  # clipped to a full bar
    p.done()
    out = tty.getvalue()
    assert "\r       mpc [" + "#" * 15 + "." * 15 + "]  50.0% half" in out
    assert "[" + "#" * 30 + "]" in out and out.endswith("\n")
