"""A child that never outlives its parent (bridge/core/lifeline.py): the parent named in the environment, read once,
and a child whose parent is already gone exits at once. The SIGKILL of a real parent: tests/integration/
test_orphans.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

from bridge.core.lifeline import PARENT_ENV, child_env, hold


def test_a_child_whose_parent_died_before_it_looked_exits_at_once() -> None:
    """The parent died between the fork and the child's ``prctl``: nobody would signal the child, so it exits."""
    code = ("import os, sys\nfrom bridge.core.lifeline import hold\n"
            "os.environ['SCMBRIDGE_PARENT_PID'] = str(os.getppid() + 1000000)\nhold()\nprint('ran on')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 128 + signal.SIGTERM and "ran on" not in res.stdout, res


def test_the_variable_is_read_once_and_not_handed_on() -> None:
    env = child_env({"A": "1"}, parent=os.getppid())
    assert env[PARENT_ENV] == str(os.getppid()) and env["A"] == "1"
    assert hold(env) in (True, False) and PARENT_ENV not in env  # armed where the kernel can; removed either way


def test_orphaned_says_whether_the_parent_named_has_died_since() -> None:
    """No parent named: never orphaned. Named and alive: not. Handed to another parent since (the kernel's
    reparenting, simulated in a child of this test): orphaned."""
    code = ("import os\nfrom bridge.core import lifeline\n"
            "before = lifeline.orphaned()\n"
            "os.environ[lifeline.PARENT_ENV] = str(os.getppid())\nlifeline.hold()\n"
            "alive = lifeline.orphaned()\nos.getppid = lambda: 1\n"
            "print(before, alive, lifeline.orphaned())\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.split() == ["False", "False", "True"], res
