"""The one kind of failure a person is expected to fix or wait out (a typo in a file, a router that is not up):
``scmbridge`` prints it as one line and exits with status 2, never a traceback."""

from __future__ import annotations


class UsageError(Exception):
    """An expected failure; ``str()`` is the one line to print (what is wrong and, where known, what to do)."""


class Denied(UsageError):
    """The lab's access control denies what was asked (the router dropped it: Zenoh tells the client nothing, the tool
    told it from its own identity and the lab's rules, :mod:`bridge.tools.identity`); ``scmbridge`` prints the one
    line and exits with :data:`EXIT`, which tells it from "nobody answered" (2)."""

    EXIT = 3
