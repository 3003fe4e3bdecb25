"""Every tool that starts processes stops all of them when it is told to stop: SIGTERM (``timeout``, CI, a desktop
session ending), SIGHUP (a closed terminal) and SIGINT (Ctrl-C). Found: ``scmbridge demo`` killed with SIGTERM left
its station and its engaged driver host running, and ``scmbridge bench fleet`` its stations and its simulator.

Each case starts the tool with a tag in its environment (inherited by every process it starts, whatever session or
process group they are in), waits until its processes are up, signals the tool only, and then finds no process
carrying the tag."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from tests.wait import until

TAG = "SCMBRIDGE_TEST_TAG"


def _tagged(tag: str) -> list[int]:
    """The pids of the live processes whose environment carries ``tag``."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            env = (entry / "environ").read_bytes()
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if f"{TAG}={tag}".encode() in env.split(b"\0") and state != "Z":
            pids.append(int(entry.name))
    return pids


def _wait(pred, timeout: float, what: str) -> None:
    if not until(pred, timeout, step=0.2):
        raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _has_socket(pid: int) -> bool:
    """Whether ``pid`` holds a socket: a tool's process has opened its Zenoh session (it is past its start-up)."""
    fds = Path("/proc") / str(pid) / "fd"
    try:
        return any(os.readlink(fd).startswith("socket:") for fd in fds.iterdir())
    except OSError:
        return False


CASES = {
    "demo": (["demo", "--duration", "60"], 3),  # the tool, its driver host and its station
    "demo --robots": (["demo", "--robots", "sig1,sig2", "--duration", "60"], 5),
    "bench fleet": (["bench", "fleet", "--sizes", "2", "--duration", "60", "--warmup", "5"], 4),  # + simulator
}


@pytest.mark.timeout(300)  # a hang guard over its own waits (90 + 90 + 60 + 10 s), not pytest's default 120 s
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT], ids=lambda s: s.name)
@pytest.mark.parametrize("case", list(CASES))
def test_a_tool_told_to_stop_leaves_no_process_behind(case: str, sig: signal.Signals, tmp_path: Path) -> None:
    if sig != signal.SIGTERM and case != "demo":
        pytest.skip("one tool is enough for SIGHUP and SIGINT: they take the same path as SIGTERM")
    args, procs = CASES[case]
    tag = uuid.uuid4().hex
    env = {**os.environ, TAG: tag, "SCMBRIDGE_STATE_DIR": str(tmp_path / "state")}
    out = ["--out", str(tmp_path / "out")] if args[0] == "demo" else []
    tool = subprocess.Popen([sys.executable, "-m", "bridge", *args, *out], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        _wait(lambda: len(_tagged(tag)) >= procs or tool.poll() is not None, 90, f"{procs} processes of {case}")
        assert tool.poll() is None, tool.communicate()[0].decode(errors="replace")[-3000:]
        # the children are past their start-up, each with its session open (a signal during an import is the same
        # case: the tool stops them all the same; this is the one a person sends to a running tool)
        _wait(lambda: all(_has_socket(p) for p in _tagged(tag)) or tool.poll() is not None, 90, f"{case}'s sessions")
        tool.send_signal(sig)
        said = tool.communicate(timeout=60)[0].decode(errors="replace")
        _wait(lambda: not _tagged(tag), 10, "no process left")
        assert tool.returncode in (128 + sig, 130, 0, 1), said[-3000:]
        assert "stop" in said.lower() or "interrupted" in said.lower(), said[-3000:]
    finally:
        for pid in _tagged(tag):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        if tool.poll() is None:
            tool.kill()
            tool.wait(timeout=10)
