"""The person's acts, authenticated where it matters (issue 31, item 4), over real Zenoh sessions on free ports.

Findings of a hostile test on the loopback default that these answer: engage and mission requests recorded from the
real CLI and replayed 60 s later drove the robot 0.09 s after; abort, start and estop release were accepted with
any claimed source; a new mission published after the goal restarted the robot with no person's act; a forged
command at seq + 1 right after each real one was applied on 341 of 341 ticks for 6 s while the driver host said
"ok, driving (cmd)"."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from bridge.core import wire as M
from bridge.core.acts import address_of, stamped
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.estop import latch_states
from bridge.tools.procs import Children
from tests.collect import Collector
from tests.wait import until

# ------------------------------------------------------------------------------------- the loopback default
SAYS = ("anyone who can reach this Zenoh session — on the loopback default, any user of this machine — may engage, "
        "start missions and release estops")


def test_without_tls_the_nodes_and_doctor_say_anyone_on_the_machine_may_command(caplog) -> None:
    from bridge.tools.doctor import check_tls

    port = free_port()
    with caplog.at_level("WARNING", logger="scmbridge"), \
            open_session(make_config(mode="peer", listen=[tcp(port)]), what="driver host"):
        pass
    assert any(SAYS in r.getMessage() and r.getMessage().startswith("driver host: ") for r in caplog.records), \
        [r.getMessage() for r in caplog.records]
    (check,) = check_tls(make_config(mode="peer", listen=[tcp(port)]), 30.0)
    assert check.level == "warn" and SAYS in check.text, check


# --------------------------------------------------------------------------------------------- helpers
def _get(session, key: str, payload: bytes, kind: type, timeout: float = 5.0):
    """The one answer to one query (sent once: a recorded request must not be re-sent by a retry)."""
    for reply in session.get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return M.decode(reply.ok.payload.to_bytes(), kind)
    return None


def _to(session, robot: str):
    """The driver host's address (its epoch and clock), as its latch answer gives it to the person's tool."""
    return address_of(_latch(session, robot))


def _stale(session, robot: str) -> dict:
    """The fields of an act addressed to the host's start but echoing its clock of a minute ago."""
    to = _to(session, robot)
    return dict(stamp=1.0, target=to.epoch, echo=max(1e-3, to.clock - 60.0), nonce=M.new_nonce())


def _latch(session, robot: str) -> M.EstopState:
    states = latch_states(session, M.key(robot, "estop"), 2.0)
    assert len(states) == 1, states
    return next(iter(states.values()))


class Sender(threading.Thread):
    """A station-like sender: its own session, one epoch, commands (v, 0) at ``hz``."""

    def __init__(self, port: int, robot: str, v: float, hz: float = 10.0) -> None:
        super().__init__(daemon=True)
        self.port, self.robot, self.v, self.period = port, robot, v, 1.0 / hz
        self.epoch = M.new_epoch()
        self.stop = threading.Event()
        self.ready = threading.Event()

    def run(self) -> None:
        with open_session(make_config(mode="client", connect=[tcp(self.port)])) as s:
            pub = s.declare_publisher(M.key(self.robot, "cmd"))
            self.ready.set()
            seq, t = 0, time.monotonic()
            while not self.stop.is_set():
                seq += 1
                pub.put(M.encode(M.Command(stamp=time.monotonic(), seq=seq, v=self.v, omega=0.0, method="scm",
                                           sender="station", epoch=self.epoch)))
                t += self.period
                self.stop.wait(max(0.0, t - time.monotonic()))


@pytest.fixture
def host(tmp_path):
    """A driver host (CAN, emulated controllers) not engaged, a client of this test's router session."""
    port, robot = free_port(), f"acts{os.getpid()}"
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        applied = col.listen(M.key(robot, "applied"), M.Applied)
        status = col.listen(M.status_key(robot, "driver"), M.Status)
        kids.spawn(["driver", "--link", "can", "--emulate", "--x0", "0,0,0", "--robot", robot, "--mode", "client",
                    "--connect", tcp(port), "--duration", "120"])
        assert col.wait(lambda: status and status[-1].state == "waiting", 60), kids.said()
        yield session, robot, port, col, applied, status


def _since(col: Collector, robot: str, t0: float) -> list[M.Applied]:
    """The applied messages received after ``t0`` (call under ``col.lock``: ``col.wait`` holds it)."""
    return [a for a, t in zip(col.got[M.key(robot, "applied")], col.times[M.key(robot, "applied")]) if t > t0]


def _applied_since(col: Collector, robot: str, t0: float) -> list[M.Applied]:
    with col.lock:
        return _since(col, robot, t0)


# --------------------------------------------------------------------------------------- engage and estop
@pytest.mark.timeout(150)
def test_a_replayed_or_unstamped_engage_or_release_does_nothing_and_says_so(host) -> None:
    session, robot, port, col, applied, status = host
    key = M.key(robot, "engage")
    station = Sender(port, robot, 0.2)
    station.start()
    try:
        assert station.ready.wait(10)
        # an old-format request (no time, no nonce): refused, says so, nothing drives
        old = _get(session, key, M.encode(M.EngageRequest(stamp=1.0, source="operator")), M.EngageState)
        assert old is not None and not old.accepted and not old.engaged and "names no process" in old.text, old
        # a person's engage, recorded off the network
        recorded = M.encode(stamped(M.EngageRequest(stamp=time.monotonic(), source="operator"), _to(session, robot)))
        ans = _get(session, key, recorded, M.EngageState)
        assert ans.accepted and ans.engaged, ans
        t_on = time.monotonic()
        assert col.wait(lambda: any(a.reason == "cmd" for a in _since(col, robot, t_on)), 5)
        # the person hands it back (a stop: always honoured, stamped or not)
        off = _get(session, key, M.encode(M.EngageRequest(stamp=1.0, engaged=False)), M.EngageState)
        assert off.accepted and not off.engaged
        t_off = time.monotonic()
        # the recorded engage replayed, and one recorded a minute ago: refused, and the robot stays stopped
        again = _get(session, key, recorded, M.EngageState)
        assert not again.accepted and not again.engaged and "already received" in again.text, again
        stale = M.EngageRequest(source="operator", **_stale(session, robot))
        ans = _get(session, key, M.encode(stale), M.EngageState)
        assert not ans.accepted and "s ago" in ans.text, ans
        # absence: the replay must not drive within 0.5 s (what it would have driven within: 0.09 s), watched while
        # the host goes on publishing (so the look is not vacuous)
        assert col.wait(lambda: any(t > t_off + 0.6 for t in col.times[M.key(robot, "applied")]), 10)
        after = _applied_since(col, robot, t_off + 0.1)
        assert after and all(a.reason == "disengaged" and a.v == 0.0 for a in after), {a.reason for a in after}
        assert col.wait(lambda: status[-1].counters.get("engage_refused_replayed") == 1
                        and status[-1].counters.get("engage_refused_stale") == 1
                        and status[-1].counters.get("engage_refused_unaddressed") == 1, 5)

        # an estop latches whatever it carries (a stop is always honoured)
        estop = M.key(robot, "estop")
        session.put(estop, M.encode(M.Estop(stamp=1.0, source="anyone", reason="test")))
        assert until(lambda: _latch(session, robot).latched, 5)
        # a release without time and nonce, or recorded and replayed, or stale: refused, and the latch says why
        session.put(estop, M.encode(M.Estop(stamp=1.0, engaged=False, source="operator")))
        assert until(lambda: "names no process" in _latch(session, robot).release_refused, 5)
        assert _latch(session, robot).latched
        release = M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"), _to(session, robot)))
        session.put(estop, release)
        assert until(lambda: not _latch(session, robot).latched, 5)
        session.put(estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="again")))
        assert until(lambda: _latch(session, robot).latched, 5)
        session.put(estop, release)  # the recorded release, replayed
        assert until(lambda: "already received" in _latch(session, robot).release_refused, 5)
        session.put(estop, M.encode(M.Estop(engaged=False, source="operator", **_stale(session, robot))))
        assert until(lambda: "s ago" in _latch(session, robot).release_refused, 5)
        assert _latch(session, robot).latched
        # the tool fills both: a person's release is taken, and then a person's engage
        cli = [sys.executable, "-m", "bridge"]
        client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
        res = subprocess.run([*cli, "estop", "--release", *client], capture_output=True, text=True, timeout=60)
        assert res.returncode == 0 and "released" in res.stdout, res.stdout + res.stderr
        res = subprocess.run([*cli, "engage", *client], capture_output=True, text=True, timeout=60)
        assert res.returncode == 0 and "engaged" in res.stdout, res.stdout + res.stderr
    finally:
        station.stop.set()
        station.join(5)


# --------------------------------------------------------------------------- two senders on one epoch
class Forger(threading.Thread):
    """Hears the station's commands and publishes a copy at seq + 1 with other velocities right after each."""

    def __init__(self, port: int, robot: str, v: float) -> None:
        super().__init__(daemon=True)
        self.port, self.robot, self.v = port, robot, v
        self.stop, self.ready = threading.Event(), threading.Event()
        self.sent = 0

    def run(self) -> None:
        with open_session(make_config(mode="client", connect=[tcp(self.port)])) as s:
            pub = s.declare_publisher(M.key(self.robot, "cmd"))

            def on_cmd(sample) -> None:
                c = M.decode(sample.payload.to_bytes(), M.Command)
                if self.stop.is_set() or c.v == self.v:
                    return
                pub.put(M.encode(M.Command(stamp=c.stamp + 0.001, seq=c.seq + 1, v=self.v, omega=0.5,
                                           method=c.method, sender=c.sender, epoch=c.epoch)))
                self.sent += 1

            sub = s.declare_subscriber(M.key(self.robot, "cmd"), on_cmd)
            self.ready.set()
            self.stop.wait()
            sub.undeclare()


@pytest.mark.timeout(150)
def test_a_forger_at_seq_plus_one_on_the_stations_epoch_stops_the_robot_and_status_says_conflict(host) -> None:
    session, robot, port, col, applied, status = host
    ans = _get(session, M.key(robot, "engage"),
               M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), _to(session, robot))), M.EngageState)
    assert ans.accepted and ans.engaged, ans
    station, forger = Sender(port, robot, 0.2), Forger(port, robot, 0.45)
    station.start()
    try:
        assert station.ready.wait(10)
        assert col.wait(lambda: status[-1].ok and any(a.reason == "cmd" and a.v == 0.2 for a in applied), 10)
        forger.start()
        assert forger.ready.wait(10)
        assert until(lambda: forger.sent > 0, 5)
        t_forge = time.monotonic()
        assert col.wait(lambda: any(a.reason == "conflict" for a in _since(col, robot, t_forge)), 2.0)
        with col.lock:
            first = min(t for a, t in zip(applied, col.times[M.key(robot, "applied")]) if t > t_forge
                        and a.reason == "conflict")
        assert first - t_forge < 0.5  # within a few ticks of the station's 10 Hz
        assert col.wait(lambda: status[-1].reason == "conflict" and not status[-1].ok, 5), status[-1]
        assert "two senders on one command epoch" in status[-1].text
        # absence: the forger goes on and the robot stays stopped the whole time: watched for 3 s at least, and on
        # until the host's stops and the forger's sends counted below have come (a stalled process takes longer)
        assert col.wait(lambda: time.monotonic() > first + 3.0 and len(_since(col, robot, first + 0.05)) > 100
                        and forger.sent > 30, 30)
        during = _applied_since(col, robot, first + 0.05)
        forged = [a for a in during if a.v == 0.45]
        assert not forged and all(a.v == 0.0 for a in during), {(a.reason, a.v) for a in during}
        assert len(during) > 100 and forger.sent > 30
        # the forger stops: once it has been silent for the silence timeout the station drives again
        forger.stop.set()
        t_quiet = time.monotonic()
        assert col.wait(lambda: any(a.reason == "cmd" and a.v == 0.2 for a in _since(col, robot, t_quiet)), 5)
    finally:
        forger.stop.set()
        station.stop.set()
        station.join(5)
        forger.join(5)


# ------------------------------------------------------------------------------ the station's mission requests
@pytest.mark.timeout(180)
def test_mission_requests_are_taken_fresh_and_once_and_a_published_mission_never_starts_the_robot(tmp_path) -> None:
    """No driver host here: the station's mission phases follow a person's requests alone (a started mission waits
    for the robot, running)."""
    port, robot = free_port(), f"actm{os.getpid()}"
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    key = M.key(robot, "control")
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        kids.spawn(["station", *client, "--store", str(tmp_path / "p.bin"), "--duration", "150"])
        assert col.wait(lambda: status and status[-1].state == "idle", 90), kids.said()

        def ask(req: M.MissionRequest | bytes) -> M.MissionState:
            ans = _get(session, key, req if isinstance(req, bytes) else M.encode(req), M.MissionState)
            assert ans is not None, "the station did not answer"
            return ans

        def req(action: str, **kw) -> M.MissionRequest:  # addressed to the station's run, as the tool does
            to = address_of(ask(M.MissionRequest(stamp=1.0, action="status")))
            return stamped(M.MissionRequest(stamp=1.0, action=action, source="operator", **kw), to)

        # an old-format start (no time, no nonce) is refused and says why; a status query needs neither
        ans = ask(M.MissionRequest(stamp=1.0, action="start", source="operator"))
        assert not ans.accepted and ans.phase == "idle" and "names no process" in ans.text, ans
        assert ask(M.MissionRequest(stamp=1.0, action="status")).accepted
        assert ask(req("start")).phase == "running"
        pause = M.encode(req("pause"))  # recorded off the network
        assert ask(pause).phase == "paused"
        assert ask(req("start")).phase == "running"
        ans = ask(pause)  # replayed
        assert not ans.accepted and ans.phase == "running" and "already received" in ans.text, ans
        to = address_of(ask(M.MissionRequest(stamp=1.0, action="status")))
        stale = M.MissionRequest(stamp=1.0, action="abort", source="operator", target=to.epoch,
                                 echo=max(1e-3, to.clock - 60.0), nonce=M.new_nonce())
        ans = ask(stale)
        assert not ans.accepted and ans.phase == "running" and "s ago" in ans.text, ans

        # a program's mission while running replaces the path in place, and says where it came from
        here = M.MissionSpec(name="program-1", path=[[0.0, 0.0], [1.0, 0.0]])
        session.put(M.key(robot, "mission"), M.encode(here))
        assert until(lambda: ask(M.MissionRequest(stamp=1.0, action="status")).mission == "program-1", 5)
        ans = ask(M.MissionRequest(stamp=1.0, action="status"))
        assert ans.phase == "running" and M.key(robot, "mission") in ans.replaced_by and ans.replaced_at > 0, ans
        # after an abort (as after the goal, or idle), a program's mission loads idle: it never starts the robot
        assert ask(req("abort")).phase == "aborted"
        session.put(M.key(robot, "mission"), M.encode(M.MissionSpec(name="program-2", path=[[0.0, 0.0], [2.0, 0.0]])))
        assert until(lambda: ask(M.MissionRequest(stamp=1.0, action="status")).mission == "program-2", 5)
        ans = ask(M.MissionRequest(stamp=1.0, action="status"))
        assert ans.phase == "idle" and "not a person's request" in ans.reason and ans.replaced_by, ans
        assert col.wait(lambda: status[-1].state == "idle" and "not a person's request" in status[-1].text, 5), \
            status[-1].text
        shown = subprocess.run([sys.executable, "-m", "bridge", "mission", "status", *client], capture_output=True,
                               text=True, timeout=60)
        assert shown.returncode == 0 and "WARNING: this mission came from" in shown.stdout, shown.stdout
        # a person starts it (the tool stamps it): running, and no longer flagged
        started = subprocess.run([sys.executable, "-m", "bridge", "mission", "start", *client], capture_output=True,
                                 text=True, timeout=60)
        assert started.returncode == 0 and "started" in started.stdout, started.stdout + started.stderr
        ans = ask(M.MissionRequest(stamp=1.0, action="status"))
        assert ans.phase == "running" and not ans.replaced_by, ans


# ------------------------------------------------------------------------------------- across a crash restart
@pytest.mark.timeout(180)
def test_a_persons_release_and_engage_recorded_before_a_crash_restart_do_nothing_after_it() -> None:
    """Finding: a person's release and engage captured off the network, the person estops, the driver host is
    SIGKILLed and restarted on the same state directory as systemd would: the release replayed 8 s after capture
    released the latch and the engage engaged the new host (the nonces lived in the dead process). Each act names
    the epoch of the start it was made for: the new start refuses them, says why, and stays latched."""
    import signal

    port, robot = free_port(), f"actr{os.getpid()}"
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    host = ["driver", "--link", "can", "--emulate", "--x0", "0,0,0", *client, "--duration", "120"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        first = kids.spawn(host)
        assert until(lambda: latch_states(session, M.key(robot, "estop"), 0.5), 60), kids.said()
        estop, key = M.key(robot, "estop"), M.key(robot, "engage")
        session.put(estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="test")))
        assert until(lambda: _latch(session, robot).latched, 5)
        release = M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"), _to(session, robot)))
        session.put(estop, release)  # the person's release, recorded
        assert until(lambda: not _latch(session, robot).latched, 5)
        engage = M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), _to(session, robot)))
        assert _get(session, key, engage, M.EngageState).engaged  # the person's engage, recorded
        session.put(estop, M.encode(M.Estop(stamp=1.0, source="operator", reason="parked")))  # the person estops
        assert until(lambda: _latch(session, robot).latched, 5)
        old_epoch = _latch(session, robot).epoch
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(10)
        kids.spawn(host)  # restarted on the same state directory: latched, from its disk
        assert until(lambda: (s := latch_states(session, M.key(robot, "estop"), 0.5))
                     and next(iter(s.values())).epoch not in (0, old_epoch), 60), kids.said()
        session.put(estop, release)  # replayed after the restart
        assert until(lambda: "another start" in _latch(session, robot).release_refused, 5)
        assert _latch(session, robot).latched
        ans = _get(session, key, engage, M.EngageState)
        assert not ans.accepted and not ans.engaged and "another start" in ans.text, ans
        # the person's own tool, against the new start: taken
        cli = [sys.executable, "-m", "bridge"]
        res = subprocess.run([*cli, "estop", "--release", *client], capture_output=True, text=True, timeout=60)
        assert res.returncode == 0 and "released" in res.stdout, res.stdout + res.stderr
        res = subprocess.run([*cli, "engage", *client], capture_output=True, text=True, timeout=60)
        assert res.returncode == 0 and "engaged" in res.stdout, res.stdout + res.stderr


@pytest.mark.timeout(180)
def test_a_persons_resume_recorded_before_a_station_restart_does_nothing_after_it(tmp_path) -> None:
    """Finding: a person's ``mission resume`` captured off the network, the station SIGKILLed and restarted (its
    mission comes back paused): the capture replayed 8.9 s later resumed the new station. It names the old run.
    (No driver host here, so the act that drives on from paused is ``start``: ``resume`` also needs the robot fit;
    both go through the same guard.)"""
    import signal

    from bridge.nodes.mission_control import Saved
    from bridge.nodes.station import control_file
    from bridge.nodes.station_tags import untagged

    port, robot = free_port(), f"acts{os.getpid()}r"
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    key = M.key(robot, "control")
    station = ["station", *client, "--store", str(tmp_path / "p.bin"), "--duration", "150"]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        first = kids.spawn(station)
        assert col.wait(lambda: status and status[-1].state == "idle", 90), kids.said()

        def ask(req) -> M.MissionState:
            ans = _get(session, key, req if isinstance(req, bytes) else M.encode(req), M.MissionState)
            assert ans is not None, "the station did not answer"
            return ans

        def addressed(action: str) -> bytes:
            to = address_of(ask(M.MissionRequest(stamp=1.0, action="status")))
            return M.encode(stamped(M.MissionRequest(stamp=1.0, action=action, source="operator"), to))

        assert ask(addressed("start")).phase == "running"
        assert ask(addressed("pause")).phase == "paused"
        resume = addressed("start")  # the person's act that drives on, recorded
        assert ask(resume).phase == "running"
        assert ask(addressed("pause")).phase == "paused"
        old = ask(M.MissionRequest(stamp=1.0, action="status")).epoch
        saved = control_file(robot)

        def saved_phase() -> str:
            try:
                return M.decode(untagged(saved.read_bytes()), Saved).phase
            except (OSError, M.MessageError):
                return ""

        assert until(lambda: saved_phase() == "paused", 10)  # kept on disk (the writer saves it after the tick)
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(10)
        kids.spawn(station)  # restarted: the saved mission comes back paused
        assert until(lambda: (a := _get(session, key, M.encode(M.MissionRequest(stamp=1.0, action="status")),
                                        M.MissionState, 1.0)) is not None and a.epoch not in (0, old), 90), kids.said()
        ans = ask(resume)  # replayed after the restart
        assert not ans.accepted and ans.phase == "paused" and "another start" in ans.text, ans
        assert ask(addressed("start")).phase == "running"  # the person's own, against the new run: taken
