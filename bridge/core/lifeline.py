"""A child that never outlives its parent: the demo's and the benches' station, driver host and emulators go away
with the process that started them, also when that process is killed with SIGKILL and can clean nothing up
(docs/ARCHITECTURE.md section 6, "No orphans").

The parent names itself in the child's environment (:data:`PARENT_ENV`, :func:`child_env`); the child, first thing
at start (:func:`hold`, called by ``python -m bridge`` before any command runs), asks the kernel for SIGTERM when its
parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``) and exits at once if the parent is already gone (it died between the
fork and the ``prctl``). SIGTERM, not SIGKILL: the child stops as on a person's Ctrl-C (a driver host sends its stop,
saves its latch and says so). The variable is removed from the child's environment once read, so a process the
child itself starts with another tool is not tied to the wrong parent. Done in the child rather than in a
``preexec_fn`` because the parents run Zenoh's threads when they fork, where ``preexec_fn`` is not safe.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from collections.abc import Mapping

#: the environment variable naming the pid whose death should stop this process
PARENT_ENV = "SCMBRIDGE_PARENT_PID"
#: prctl(2): the signal the calling process gets when its parent dies
PR_SET_PDEATHSIG = 1
#: the parent :func:`hold` was named (None: none was)
_held_parent: int | None = None


def child_env(env: Mapping[str, str] | None = None, parent: int | None = None) -> dict[str, str]:
    """``env`` (this process's environment by default) with :data:`PARENT_ENV` naming ``parent`` (this process)."""
    out = dict(os.environ if env is None else env)
    out[PARENT_ENV] = str(os.getpid() if parent is None else parent)
    return out


def _pdeathsig(sig: int) -> bool:
    """Ask the kernel for ``sig`` when the parent dies; False where it cannot (not Linux, no libc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def hold(environ: dict[str, str] | None = None) -> bool:
    """If the environment names a parent: SIGTERM this process when that parent dies, and exit now (status 143, as
    SIGTERM's) if it has died already. Returns whether a parent was named and the kernel will signal."""
    env = os.environ if environ is None else environ
    named = env.pop(PARENT_ENV, None)
    if not named:
        return False
    try:
        parent = int(named)
    except ValueError:
        return False
    global _held_parent
    _held_parent = parent
    armed = _pdeathsig(signal.SIGTERM)
    if os.getppid() != parent:  # the parent died before the kernel was asked: nobody would signal us
        os._exit(128 + signal.SIGTERM)
    return armed


def orphaned() -> bool:
    """Whether the parent :func:`hold` was named has died since (this process was handed to another). Its SIGTERM
    came then, but a process still starting may not have acted on it: the start-up's handler raises it in the main
    thread, and an exception raised in a finaliser (a collection runs them anywhere) is printed and dropped. A node
    asks this once its own stop handler is in place (:func:`bridge.nodes.node.stop_on_signals`)."""
    return _held_parent is not None and os.getppid() != _held_parent


__all__ = ["PARENT_ENV", "child_env", "hold", "orphaned"]
