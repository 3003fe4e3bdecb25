"""Child processes that always go away: started in their own process group, stopped with bounded waits."""

from __future__ import annotations

import os
import signal
import subprocess


def stop_group(proc: subprocess.Popen, term_timeout: float = 10.0) -> None:
    """SIGTERM the child's whole process group, SIGKILL it if it has not gone after ``term_timeout`` s.

    The child must have been started with ``start_new_session=True`` (its pid is its group id)."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=term_timeout)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=5)
    except ProcessLookupError:
        proc.wait(timeout=5)
