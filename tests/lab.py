"""What the tests that run the lab's processes share (tests/integration/test_router.py,
tests/integration/test_lab_in_a_box.py): polling another process's answers, and the Zenoh router started as a
process of its own (``scmbridge router``, deploy/README.md) and waited for until it listens."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from typing import TypeVar

from bridge.tools.procs import Children, said

T = TypeVar("T")


def until(fn: Callable[[], T], timeout: float, step: float = 0.5) -> T:
    """``fn()`` once it is truthy, or its last value after ``timeout`` s, looked at every ``step`` s (each look is
    a question to another process, such as a ``scmbridge status`` run: there is no event of this process to await)."""
    t_end = time.monotonic() + timeout
    while True:
        res = fn()
        if res or time.monotonic() > t_end:
            return res
        time.sleep(step)


def start_router(kids: Children, *args: str, duration: str = "220") -> subprocess.Popen:
    """``scmbridge router ARGS... --duration DURATION`` as one of ``kids`` (stopped with them), returned once it
    says it listens (at most 60 s); fails the test, with what it said, if it exits instead."""
    router = kids.spawn(["router", *args, "--duration", duration])
    assert until(lambda: "listening on" in said(router) or router.poll() is not None, 60, 0.2), said(router)
    assert router.poll() is None, said(router)
    return router
