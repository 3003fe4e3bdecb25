"""A lab in a box: the secure deployment exactly as deploy/README.md lays it out, on loopback. `deploy lab` makes a CA
and the certificates, the router's TLS + access-control config (`scmbridge router`, a process of its own) and the
clients' configs; the station, a robot's driver host and the operator's tools are TLS clients: a person engages the
robot, starts the mission, sees it drive in `status --all`, stops it with `estop --all`; the observer sees everything
and can change nothing, and is told so ("denied", exit 3), not "nobody answered". Findings this answers: under the
lab's TLS + access control `estop --all` did nothing and the operator's tools saw nothing; an observer's engage said
"no driver host answered"."""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from bridge.core.config import load_mission
from bridge.nodes.zsession import free_port
from bridge.tools.procs import Children
from tests.lab import start_router
from tests.wait import until

ROBOT = "rover1"


def _scm(*args: str, timeout: float = 90) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bridge", *args], capture_output=True, text=True, timeout=timeout)


def _first_ok(run: Callable[[], subprocess.CompletedProcess], timeout: float) -> subprocess.CompletedProcess:
    """The first of ``run()``'s tool runs that exits 0 within ``timeout`` s (one every half second), or else the last
    one: a failure shows what the tool said last."""
    last: list[subprocess.CompletedProcess] = []

    def ok() -> bool:
        last.append(run())
        return last[-1].returncode == 0

    until(ok, timeout, 0.5)
    return last[-1]


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
@pytest.mark.timeout(240)
def test_a_secure_lab_on_loopback_is_driven_and_stopped_by_its_operator(tmp_path: Path) -> None:
    # the whole lab in one command (the certificates are used where they were made)
    made = _scm("deploy", "lab", "--robots", ROBOT, "--station-address", "127.0.0.1", "--port", str(free_port()),
                "--certs", str(tmp_path / "tls"), "--out", str(tmp_path))
    assert made.returncode == 0, made.stderr
    z = {n: ["--zenoh-config", str(tmp_path / f"{n}.json5")] for n in (ROBOT, "operator", "observer")}
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    with Children() as kids:
        start_router(kids, "--zenoh-config", str(tmp_path / "router.json5"))
        kids.spawn(["station", "--robot", ROBOT, "--zenoh-config", str(tmp_path / "station-client.json5"), "--store",
                    str(tmp_path / "pairs.bin"), "--duration", "200"])
        kids.spawn(["driver", "--link", "can", "--emulate", "--x0", x0, "--robot", ROBOT, *z[ROBOT], "--duration",
                    "200"])
        # the operator sees both nodes: idle and waiting for a person
        def both() -> subprocess.CompletedProcess | None:
            r = _scm("status", "--all", *z["operator"])
            rows = {tuple(ln.split()[:3]) for ln in r.stdout.splitlines()}
            return r if (ROBOT, "station", "idle") in rows and any(x[:2] == (ROBOT, "driver") for x in rows) else None

        seen = until(both, 120, 0.5)  # (a deadline: a loaded machine's station may take a minute to come up)
        assert seen and "waiting" in seen.stdout, seen and seen.stdout + seen.stderr
        for cmd in (["engage", "--robot", ROBOT], ["mission", "start", "--robot", ROBOT]):
            res = _scm(*cmd, "--timeout", "30", *z["operator"])  # a deadline on the answer, not a wait
            assert res.returncode == 0, res.stdout + res.stderr
        driving = _first_ok(lambda: _scm("status", "--robot", ROBOT, *z["observer"]), 60)
        assert driving.returncode == 0 and "driving" in driving.stdout, driving.stdout + driving.stderr + kids.said()
        # the observer can change nothing, and is told it is denied (exit 3), not that nobody answered (exit 2)
        for cmd in (["engage", "--robot", ROBOT, "--release"], ["mission", "pause", "--robot", ROBOT],
                    ["estop", "--robot", ROBOT]):
            res = _scm(*cmd, "--timeout", "2", *z["observer"])
            assert res.returncode == 3 and "denied: identity 'observer' (role observer)" in res.stderr, res.stderr
        # calibrate drives as the station does: with the operator's identity it is denied at once
        res = _scm("calibrate", "--robot", ROBOT, *z["operator"])
        assert res.returncode == 3 and "station's identity" in res.stderr, res.stderr
        # the preflight through the lab's TLS and rules: the operator's identity sees both nodes
        doc = _scm("doctor", *z["operator"])
        assert doc.returncode == 0 and "ok    reach" in doc.stdout and "1 driver hosts answer" in doc.stdout, doc.stdout
        assert "ok    tls" in doc.stdout and "FAIL" not in doc.stdout, doc.stdout
        # the operator stops every robot
        res = _scm("estop", "--all", *z["operator"])
        assert res.returncode == 0 and f"{ROBOT}/driver-can: LATCHED by operator" in res.stdout, res.stdout + res.stderr
        stopped = until(lambda: "estop latched by operator" in _scm("status", "--all", *z["observer"]).stdout, 30,
                        0.5)
        assert stopped


def _documented(name: str, *words: str, without: tuple[str, ...] = ()) -> list[str]:
    """The arguments of the command ``scmbridge NAME ...`` the deployment docs show with these words (and none of
    ``without``), as written."""
    from tests.repo.test_docs_commands import documented

    for _, n, args in documented():
        if (n == name and "operator.json5" in args and all(w in args for w in words)
                and not any(w in args for w in without)):
            return [*name.split(), *args]
    raise AssertionError(f"the docs show no `scmbridge {name} {' '.join(words)} --zenoh-config operator.json5`")


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
@pytest.mark.timeout(240)
def test_the_operators_documented_commands_run_as_written_in_the_lab(tmp_path: Path) -> None:
    """deploy/README.md's and deploy/ROBOT.md's operator commands (``--zenoh-config operator.json5``), word for word,
    run from the directory `deploy lab` wrote: the preflight, engage, start, status (once and --watch), estop and its
    release."""
    made = _scm("deploy", "lab", "--robots", ROBOT, "--station-address", "127.0.0.1", "--port", str(free_port()),
                "--certs", str(tmp_path / "tls"), "--out", str(tmp_path))
    assert made.returncode == 0, made.stderr
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)

    def scm(args: list[str], timeout: float = 90) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "bridge", *args], capture_output=True, text=True,
                              timeout=timeout, cwd=tmp_path)

    with Children() as kids:
        start_router(kids, "--zenoh-config", str(tmp_path / "router.json5"))
        kids.spawn(["station", "--robot", ROBOT, "--zenoh-config", str(tmp_path / "station-client.json5"), "--store",
                    str(tmp_path / "pairs.bin"), "--duration", "200"])
        kids.spawn(["driver", "--link", "can", "--emulate", "--x0", x0, "--robot", ROBOT, "--zenoh-config",
                    str(tmp_path / f"{ROBOT}.json5"), "--duration", "200"])
        doctor = until(lambda: (r := scm(_documented("doctor"))).returncode == 0 and "1 driver hosts answer"
                        in r.stdout and r, 60, 0.5)
        assert doctor, "the documented doctor never passed"
        for name in ("engage", "mission start"):
            res = scm(_documented(name, "--robot"))
            assert res.returncode == 0, (name, res.stdout + res.stderr)
        once = _documented("status", "--robot")
        driving = _first_ok(lambda: scm(once), 60)
        assert driving.returncode == 0 and "driving" in driving.stdout, driving.stdout + driving.stderr + kids.said()
        # its stderr into a file: a pipe nobody reads blocks a child that logs 64 KB (Zenoh's warnings under load),
        # and a blocked child cannot obey its Ctrl-C
        errors = tempfile.TemporaryFile()  # noqa: SIM115 (closed below)
        watch = subprocess.Popen([sys.executable, "-m", "bridge", *_documented("status", "--all", "--watch")],
                                 stdout=subprocess.PIPE, stderr=errors, text=True, cwd=tmp_path,
                                 start_new_session=True)
        try:
            first = [watch.stdout.readline() for _ in range(2)]
            assert all(line.startswith(ROBOT) for line in first), first
            watch.send_signal(2)  # Ctrl-C
            try:
                code = watch.wait(timeout=30)
            except subprocess.TimeoutExpired:  # where it waits: every thread's stack (`kill -USR2`), then fail
                watch.send_signal(signal.SIGUSR2)
                # a window, only on the way to a failure: the stack dumps SIGUSR2 asks for are written meanwhile
                time.sleep(2.0)
                errors.seek(0)
                pytest.fail(f"status --watch did not stop within 30 s of Ctrl-C:\n{errors.read().decode()[-6000:]}")
            errors.seek(0)
            assert code == 0, errors.read()[-3000:]
        finally:
            if watch.poll() is None:
                watch.kill()
                watch.wait()
            errors.close()
        res = scm(_documented("estop", "--robot"))
        assert res.returncode == 0 and "LATCHED by operator" in res.stdout, res.stdout + res.stderr
        res = scm(_documented("estop", "--robot", "--release"))
        assert res.returncode == 0 and "released" in res.stdout, res.stdout + res.stderr
        res = scm(_documented("estop", "--all", without=("--fleet",)))  # the fleet file is /etc's
        assert res.returncode == 0 and "LATCHED by operator" in res.stdout, res.stdout + res.stderr
