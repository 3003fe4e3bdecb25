"""The Zenoh router the lab's tests start as a process of its own (``scmbridge router``, deploy/README.md), waited
for until it listens: tests/integration/test_router.py, tests/integration/test_lab_in_a_box.py."""

from __future__ import annotations

import subprocess

from bridge.tools.procs import Children, said
from tests.wait import until


def start_router(kids: Children, *args: str, duration: str = "220") -> subprocess.Popen:
    """``scmbridge router ARGS... --duration DURATION`` as one of ``kids`` (stopped with them), returned once it
    says it listens (at most 60 s); fails the test, with what it said, if it exits instead."""
    router = kids.spawn(["router", *args, "--duration", duration])
    assert until(lambda: "listening on" in said(router) or router.poll() is not None, 60, 0.2), said(router)
    assert router.poll() is None, said(router)
    return router
