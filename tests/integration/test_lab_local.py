"""The secure lab on one machine, as deploy/README.md ("The whole lab on one machine") writes it: every line of that
block run as written, in a fresh directory (the services as processes of their own, each with the state directory
the line gives it; the tools one after the other). Findings this answers: `deploy lab --out lab/` wrote
/etc/scmbridge/tls/... into every config and the router exited with "Invalid TLS private key file: No such file or
directory" without naming the file; `--certs` and `--port` were needed and not documented, nor the station's and the
driver host's command lines, nor a state directory per host; the observer's engage was denied after 40 s."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bridge.tools.procs import Children, said
from tests.wait import until

README = Path(__file__).resolve().parents[2] / "deploy" / "README.md"
SERVICES = ("router", "station", "driver")


def documented_lab() -> list[tuple[dict[str, str], list[str]]]:
    """The block's lines: (the environment the line sets, the scmbridge arguments), comments left out."""
    text = README.read_text().split("## The whole lab on one machine", 1)[1]
    block = re.search(r"```\n(.*?)```", text, flags=re.S).group(1)
    out = []
    for raw in block.splitlines():
        words = shlex.split(raw.split(" #", 1)[0])
        if not words:
            continue
        at = words.index("scmbridge")
        env = dict(w.split("=", 1) for w in words[:at])
        out.append((env, words[at + 1:]))
    return out


def _row(res: subprocess.CompletedProcess, node: str) -> list[str]:
    """The words of ``status``'s line for rover1's ``node`` (empty if none)."""
    return next((ln.split() for ln in res.stdout.splitlines() if ln.split()[:2] == ["rover1", node]), [])


def _scm(args: list[str], cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
@pytest.mark.timeout(300)
def test_the_documented_local_lab_runs_as_written(tmp_path: Path) -> None:
    lines = documented_lab()
    names = [a[0] for _, a in lines]
    assert names[:4] == ["deploy", *SERVICES] and "engage" in names and "estop" in names, names
    with Children() as kids:
        services = {}
        for env, args in lines:
            if args[0] == "deploy":
                res = _scm(args, tmp_path)
                assert res.returncode == 0, res.stdout + res.stderr
                assert "/etc/scmbridge" not in (tmp_path / "lab" / "router.json5").read_text()
                continue
            if args[0] in SERVICES:  # bounded here; a person stops them with Ctrl-C
                services[args[0]] = kids.spawn([*args, "--duration", "240"], env={**os.environ, **env},
                                               cwd=tmp_path)
                continue
            what = " ".join(args)
            if args[:2] == ["status", "--all"]:  # the first look: both nodes up (they take a moment to start)
                def both(args: list[str] = args) -> subprocess.CompletedProcess | None:
                    r = _scm(args, tmp_path)
                    rows = {tuple(ln.split()[:3]) for ln in r.stdout.splitlines()}
                    return r if ("rover1", "station", "idle") in rows and ("rover1", "driver", "missing") not in rows \
                        and any(x[:2] == ("rover1", "driver") for x in rows) else None

                res = until(both, 120, 0.5)
                assert res, f"{what}: {[said(p) for p in services.values()]}"
            elif args[0] == "status":  # the observer reads what the operator started: the robot moves, measured
                res = until(lambda args=args: (r := _scm(args, tmp_path)).returncode == 0 and _row(r, "driver")[2:3]
                            == ["moving"] and r, 60, 0.5)
                assert res, f"{what}: {_scm(args, tmp_path).stdout}"
            elif "--release" in args and "lab/observer.json5" in args:
                # denied, and said at once: well inside engage's own wait for a driver host (40 s)
                res = _scm(args, tmp_path, timeout=20)
                assert res.returncode == 3 and "denied: identity 'observer'" in res.stderr, res.stderr
            else:
                res = _scm(args, tmp_path, timeout=90)
                assert res.returncode == 0, (what, res.stdout + res.stderr)
                if args[0] == "estop":
                    assert "rover1/driver-can: LATCHED by operator" in res.stdout, res.stdout
                    # and it stands: "stopped", measured, never "driving"
                    look = ["status", "--robot", "rover1", "--zenoh-config", "lab/observer.json5"]
                    still = until(lambda look=look: _row(_scm(look, tmp_path), "driver")[2:3] == ["stopped"], 30, 0.5)
                    assert still, _scm(look, tmp_path).stdout
        # each host kept its own state: the driver host's estop latch in its directory, none in the station's
        assert list((tmp_path / "lab" / "state" / "rover1").glob("estop-rover1*"))
        assert not list((tmp_path / "lab" / "state" / "station").glob("estop-*"))
        assert all(p.poll() is None for p in services.values()), kids.said()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
def test_a_missing_certificate_is_named_with_the_fix(tmp_path: Path) -> None:
    res = _scm(["deploy", "lab", "--local", "--robots", "rover1", "--out", "lab"], tmp_path)
    assert res.returncode == 0, res.stderr
    (tmp_path / "lab" / "tls" / "station.key").unlink()
    (tmp_path / "lab" / "tls" / "operator.crt").unlink()
    router = _scm(["router", "--zenoh-config", "lab/router.json5", "--duration", "5"], tmp_path)
    tool = _scm(["status", "--all", "--zenoh-config", "lab/operator.json5"], tmp_path)
    assert router.returncode == 2 and "lab/tls/station.key" in router.stderr, router.stderr
    assert tool.returncode == 2 and "lab/tls/operator.crt" in tool.stderr, tool.stderr
    for r in (router, tool):
        assert "no such file" in r.stderr and "deploy lab --local" in r.stderr and "Traceback" not in r.stderr
