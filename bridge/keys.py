"""Zenoh key expressions, one namespace per robot: ``scm/<robot>/<topic>`` (DESIGN.md section 4)."""

from __future__ import annotations

import re

PREFIX = "scm"
TOPICS = ("state", "cmd", "teacher", "applied", "pairs", "status", "estop")
_ROBOT = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_robot(robot: str) -> str:
    """A robot name is one key chunk: letters, digits, ``_`` and ``-`` (no ``/``, ``*``, ``$``, ``?``, ``#``)."""
    if not _ROBOT.match(robot):
        raise ValueError(f"robot name {robot!r} must be 1-64 characters of [A-Za-z0-9_-]")
    return robot


def key(robot: str, topic: str) -> str:
    """The key of ``topic`` for ``robot``, e.g. ``key("rover1", "cmd") == "scm/rover1/cmd"``."""
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r}; topics: {', '.join(TOPICS)}")
    return f"{PREFIX}/{check_robot(robot)}/{topic}"


def status_key(robot: str, node: str) -> str:
    """Each node publishes its health under its own sub-key so several nodes' status do not overwrite."""
    return f"{key(robot, 'status')}/{check_robot(node)}"


class Keys:
    """All keys of one robot, as attributes: ``Keys("rover1").cmd == "scm/rover1/cmd"``."""

    def __init__(self, robot: str) -> None:
        self.robot = check_robot(robot)
        for topic in TOPICS:
            setattr(self, topic, key(robot, topic))

    state: str
    cmd: str
    teacher: str
    applied: str
    pairs: str
    status: str
    estop: str
