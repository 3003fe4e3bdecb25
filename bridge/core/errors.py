"""The one kind of failure a person is expected to fix or wait out (a typo in a file, a router that is not up):
``scmbridge`` prints it as one line and exits with status 2, never a traceback."""

from __future__ import annotations


class UsageError(Exception):
    """An expected failure; ``str()`` is the one line to print (what is wrong and, where known, what to do)."""
