"""No process outlives its parent: the children the demo and the benches start (``bridge.tools.procs``) go away when
their parent is killed with SIGKILL, which lets it clean nothing up (finding: ``kill -9`` of ``scmbridge demo``
left its station and driver host running under PID 1 until their ``--duration``, 120-150 s)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from bridge.core import wire as M
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from tests.collect import Collector
from tests.wait import until

PARENT = textwrap.dedent("""
    import sys, time
    from bridge.tools.procs import Children
    port = int(sys.argv[1])
    with Children() as kids:
        router = kids.spawn(["router", "--listen", f"tcp/127.0.0.1:{port}", "--duration", "300"])
        host = kids.spawn(["driver", "--link", "can", "--emulate", "--x0", "0,0,0", "--robot", "orphan",
                           "--mode", "client", "--connect", f"tcp/127.0.0.1:{port}", "--duration", "300"])
        print(router.pid, host.pid, flush=True)
        time.sleep(300)  # the parent idles until the test kills it (-9): its children must not outlive it
""")


def _alive(pid: int) -> bool:
    """``pid`` exists and is not a zombie (a reaped-later child of PID 1 is gone for every purpose)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.timeout(120)
def test_the_children_die_with_their_parent_on_sigkill() -> None:
    port = free_port()
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(port)], stdout=subprocess.PIPE, text=True,
                              start_new_session=True)
    pids: list[int] = []
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == 2 and all(_alive(p) for p in pids), pids
        # the driver host is up (its session open, its loop publishing its status), not merely forked
        give_up = threading.Timer(60, (stop := threading.Event()).set)  # the router may still be starting
        give_up.start()
        with open_session(make_config(mode="client", connect=[tcp(port)]), wait=stop) as session:
            give_up.cancel()
            col = Collector(session)
            drv = col.listen(M.status_key("orphan", "driver"), M.Status)
            assert col.wait(lambda: drv and drv[-1].state != "starting", 90), [s.text for s in drv[-2:]]
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(timeout=10)
        gone = until(lambda: not any(_alive(p) for p in pids), 30, 0.1)
        assert gone, [p for p in pids if _alive(p)]
    finally:
        for p in pids:  # a failure must not leave them behind either
            if _alive(p):
                os.killpg(p, signal.SIGKILL)
        if parent.poll() is None:
            parent.kill()
            parent.wait()


def _children(pid: int) -> dict[int, str]:
    """The live children of ``pid``: their pid and command line."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid and fields[0] != "Z":
                with open(f"/proc/{d}/cmdline", "rb") as f:
                    out[int(d)] = f.read().replace(b"\0", b" ").decode(errors="replace")
        except (OSError, IndexError, ValueError):
            continue
    return out


def _why_alive(alive: dict[int, str], out: Path) -> str:
    """For a failure's message: each live child's command line, state, kernel wait channel and signal masks (a
    SIGTERM pending but blocked shows in SigPnd/ShdPnd and SigBlk), then what the demo's children wrote last, with
    the Python stack of each of their threads: SIGUSR2 makes every ``scmbridge`` process write them to its stderr
    (``faulthandler``, from its C handler: also where the main thread is stuck in native code)."""
    lines = []
    for pid in alive:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGUSR2)
    until(lambda: sum("(most recent call first)" in p.read_text(errors="replace") for p in out.glob("*.log"))
          >= len(alive), 2.0, 0.05)
    for pid, cmd in alive.items():
        lines.append(f"pid {pid}: {cmd[:200]}")
        try:
            status = Path(f"/proc/{pid}/status").read_text().splitlines()
            lines += [f"  {x}" for x in status if x.split(":")[0] in ("State", "Threads", "SigPnd", "ShdPnd", "SigBlk",
                                                                    "SigIgn", "SigCgt")]
            lines.append(f"  wchan: {Path(f'/proc/{pid}/wchan').read_text()}")
        except OSError as exc:
            lines.append(f"  ({exc})")
    for log in sorted(out.glob("*.log")):
        lines.append(f"--- {log.name} (last 6000 characters):\n{log.read_text(errors='replace')[-6000:]}")
    return "\n".join(lines)


@pytest.mark.timeout(240)
def test_kill_9_of_the_demo_takes_its_station_and_driver_host_with_it(tmp_path) -> None:
    """The finding as it was met: ``kill -9`` of ``scmbridge demo`` left its station and driver host running."""
    demo = subprocess.Popen([sys.executable, "-m", "bridge", "demo", "--duration", "150", "--out", str(tmp_path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    kids: dict[int, str] = {}
    try:
        def both() -> bool:
            kids.update(_children(demo.pid))
            return any(" driver " in c for c in kids.values()) and any(" station " in c for c in kids.values())

        assert until(both, 120, 0.2), kids
        os.kill(demo.pid, signal.SIGKILL)
        demo.wait(timeout=10)
        gone = until(lambda: not any(_alive(p) for p in kids), 60, 0.2)
        assert gone, _why_alive({p: c for p, c in kids.items() if _alive(p)}, tmp_path)
    finally:
        for p in kids:
            if _alive(p):
                os.killpg(p, signal.SIGKILL)
        if demo.poll() is None:
            demo.kill()
            demo.wait()
