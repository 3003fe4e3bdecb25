"""Child processes that always go away: started in their own process group, stopped with bounded waits."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bridge.core import ports
from bridge.core.auth import make_key
from bridge.core.lifeline import child_env


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


#: ``out`` of :func:`spawn`: the child's output goes to an anonymous temporary file, read back with :func:`said`
LOG = "log"


def spawn(args: list[str], out: Any = LOG, prefix: tuple[str, ...] = (), **kwargs: Any) -> subprocess.Popen:
    """``scmbridge ARGS...`` as a child in its own process group (so :func:`stop_group` takes all of it), with
    stdout and stderr together into ``out``: :data:`LOG` (the default), a temporary file that never fills, read
    with :func:`said`; a file; ``subprocess.DEVNULL``; or ``subprocess.PIPE`` for a caller that reads as the child
    writes (a pipe nobody reads blocks a chatty child once it holds 64 KB). The child goes away with this process,
    also when this one is killed with SIGKILL (:mod:`bridge.core.lifeline`; ``env`` is kept, with this process named
    as its parent). ``prefix``: a command that runs it (``ip netns exec NS``: in a network namespace of its own)."""
    kwargs["env"] = child_env(kwargs.get("env"))
    log = tempfile.TemporaryFile() if isinstance(out, str) and out == LOG else None  # noqa: SIM115 (closed by Children)
    proc = subprocess.Popen([*prefix, sys.executable, "-m", "bridge", *args], stdout=log if log is not None else out,
                            stderr=subprocess.STDOUT, start_new_session=True, **kwargs)
    proc.log = log  # type: ignore[attr-defined]
    return proc


def said(proc: subprocess.Popen, tail: int = 3000) -> str:
    """The last ``tail`` characters a child spawned with :data:`LOG` wrote (empty for any other ``out``)."""
    log = getattr(proc, "log", None)
    if log is None or log.closed:
        return ""
    log.seek(0, os.SEEK_END)
    log.seek(max(0, log.tell() - 4 * tail))
    return log.read().decode(errors="replace")[-tail:]


class Children:
    """The children of one run: ``with Children() as kids: kids.spawn([...])``; all stopped on exit, newest first."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def spawn(self, args: list[str], out: Any = LOG, prefix: tuple[str, ...] = (), **kwargs: Any) -> subprocess.Popen:
        proc = spawn(args, out, prefix, **kwargs)
        self.procs.append(proc)
        return proc

    def said(self) -> str:
        """What every child spawned with :data:`LOG` said last, each under its command line (for a failure's
        message)."""
        return "".join(f"\n--- {' '.join(p.args[3:6])} ... (exit {p.poll()}):\n{said(p, 1500)}" for p in self.procs
                       if getattr(p, "log", None) is not None)

    def any_exited(self) -> bool:
        return any(p.poll() is not None for p in self.procs)

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc: object) -> None:
        for p in reversed(self.procs):
            stop_group(p)
        for p in self.procs:
            if getattr(p, "log", None) is not None:
                p.log.close()


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port free right now on ``host`` (never a fixed port), drawn where no other socket's port 0 takes it
    meanwhile (:func:`bridge.core.ports.free_port`)."""
    return ports.free_port(host, socket.SOCK_DGRAM)


def emulated_link(kids: Children, link: str, workdir: Path, x0: str, duration: float, out: Any = subprocess.DEVNULL,
                  rate_hz: float = 20.0) -> list[str]:
    """Start the emulated learner for ``link`` the way a real robot would sit on it, and return the driver host's
    ``--link ...`` arguments that reach it: CAN controllers live inside the driver host (``--emulate``: this
    machine has no CAN across processes), the UDP robot and the rover are processes of their own on loopback."""
    if link == "can":
        return ["--link", "can", "--emulate", "--x0", x0]
    port = free_udp_port()
    cfg = Path(workdir) / f"driver-{link}.toml"
    key = Path(workdir) / f"{link}-{port}.key"  # both ends authenticate, as a lab's robot does
    make_key(key, force=True)
    extra = ["--key-file", str(key)]
    if link == "udp":  # the robot and the driver host each answer only the other's configured address
        bind = free_udp_port()
        cfg.write_text(f'[link.udp]\nrobot_host = "127.0.0.1"\nrobot_port = {port}\nbind_port = {bind}\n'
                       f'key_file = "{key}"\n')
        extra += ["--peer", f"127.0.0.1:{bind}"]
    else:
        cfg.write_text(f'[link.mavlink]\nurl = "udpout:127.0.0.1:{port}"\nrate_hz = {rate_hz}\n'
                       f'signing_key_file = "{key}"\n')
    kids.spawn(["learner", "--link", link, "--port", str(port), "--x0", x0, "--duration", str(duration), *extra],
               out)
    return ["--link", link, "--config", str(cfg)]
