"""What a person is told is true when asked, and says the next step (issue 32, found by a new lab user on one machine).

- A request right after a confirmed engage or release is judged on the robot as it is then: the driver host
  publishes its status at once when it changes (not only each second) and the station hears it before answering.
- ``status``: every reason current (gone with its cause), a robot parked at its goal is ``parked``, a missing node
  is named, an estop is not ok even when the mission is finished, a restarted station shows its mission's phase and
  progress, a paused mission says ``scmbridge mission resume`` once the robot is fit again.
- A MAVLink host never engaged does not say the operator "took control" of a vehicle it found in MANUAL.
- ``mission start`` with the robot at the goal is refused, saying how to drive back (``mission send --reverse``).

The nodes run as real processes on free ports (the emulated CAN learner), the operator's acts are the tools' own
queries sent back to back from this process (no process start-up between them to hide a late status), and once as
the commands a person types, chained with ``&&``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from bridge.core import wire as M
from bridge.core.acts import stamped
from bridge.core.config import StationConfig, load_mission, load_mission_spec
from bridge.nodes.mission_control import Fitness, MissionControl, spec_of
from bridge.nodes.station_core import StationCore, TickInputs
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools import engage as engage_tool
from bridge.tools import mission as mission_tool
from bridge.tools.estop import confirm
from bridge.tools.procs import Children
from bridge.tools.status import report as status_report
from bridge.tools.status import robot_ok
from tests.collect import Collector

FIT = M.Status(stamp=0.0, seq=1, node="driver", ok=True, state="driving", reason="ok", text="link can: driving (cmd)")


def _driver(seq: int, ok: bool = True, state: str = "driving", reason: str = "ok", text: str = "") -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=ok, state=state, reason=reason, text=text)


def _pose(x: float, y: float, theta: float = 0.0, seq: int = 1) -> M.LearnerState:
    return M.LearnerState(stamp=1.0, seq=seq, x=x, y=y, theta=theta)


# ------------------------------------------------------------------------------------------------ the station
def test_a_paused_missions_reason_is_the_robots_reason_now_and_says_how_to_resume(tmp_path) -> None:
    mission = load_mission()
    x0, y0, th = (float(a) for a in mission.start)
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission)
    core.request(M.MissionRequest(stamp=0.0, action="start", source="test"), 0.0)
    now, seq = 1.0, 0

    def tick(driver: M.Status | None, pose: bool = True) -> M.Status:
        nonlocal now, seq
        now += 0.1
        seq += 1
        tel = ((M.LearnerState(stamp=now, seq=seq, x=x0, y=y0, theta=th), now),) if pose else ()
        core.tick(TickInputs(telemetry=tel, driver=(driver, now) if driver is not None else None), now)
        return core.status(now)

    for _ in range(3):
        st = tick(_driver(seq))
    assert st.state == "driving", st.text
    # an estop pauses the mission: the status says the estop while it is latched ...
    st = tick(_driver(seq, False, "estop", "estop", "link can: estop latched by operator"))
    assert st.state == "paused" and "estop latched by operator" in st.text, st.text
    # ... and once released, no longer: the robot is ready, resume to drive on
    st = tick(_driver(seq))
    assert st.state == "paused" and "estop" not in st.text, st.text
    assert "scmbridge mission resume --robot r1" in st.text, st.text
    ans = core.request(M.MissionRequest(stamp=now, action="status"), now)
    assert "estop" not in ans.reason and "mission resume --robot r1" in ans.reason, ans
    # a driver host crash: poses stop, the mission pauses on them; back, the pose reason goes with its cause
    core.request(M.MissionRequest(stamp=now, action="resume", source="test"), now)
    tick(_driver(seq))
    for _ in range(30):
        st = tick(_driver(seq), pose=False)
    assert st.state == "paused" and "no pose for" in st.text, st.text
    st = tick(_driver(seq))
    assert "no pose" not in st.text and "mission resume --robot r1" in st.text, st.text
    # a person's pause stays said (it is still true), with the next step
    core.request(M.MissionRequest(stamp=now, action="resume", source="test"), now)
    tick(_driver(seq))
    core.request(M.MissionRequest(stamp=now, action="pause", source="alice"), now)
    st = tick(_driver(seq))
    assert "paused by alice" in st.text and "mission resume --robot r1" in st.text, st.text


def test_a_request_is_judged_on_the_driver_status_heard_since_the_last_tick(tmp_path) -> None:
    """The adapter hands the newest driver host status to the core before a request (note_driver): a release heard
    a moment ago lets a start through, without waiting for the next tick."""
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", load_mission())
    pose = _pose(*(float(a) for a in load_mission().start))
    core.tick(TickInputs(telemetry=((pose, 1.0),), driver=(_driver(1, False, "estop", "estop", "estop"), 1.0)), 1.0)
    core.note_driver(_driver(2), 1.05)  # the release, heard between two ticks
    ans = core.request(M.MissionRequest(stamp=1.05, action="start", source="test"), 1.05)
    assert ans.accepted and core.control.phase == "running", ans


def test_a_robot_parked_at_its_goal_is_parked_and_a_start_there_is_refused_with_the_way_back(tmp_path) -> None:
    mission = load_mission()
    gx, gy = (float(a) for a in mission.goal)
    core = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", mission)
    core.request(M.MissionRequest(stamp=0.0, action="start", source="test"), 0.0)
    for k in range(3):
        now = 1.0 + 0.1 * k
        core.tick(TickInputs(telemetry=((M.LearnerState(stamp=now, seq=k, x=gx, y=gy, theta=0.0), now),),
                             driver=(_driver(k + 1), now)), now)
    st = core.status(now)
    assert core.control.phase == "finished" and st.state == "parked" and st.ok and st.progress == 1.0, st
    ans = core.request(M.MissionRequest(stamp=now, action="start", source="test"), now)
    assert not ans.accepted and "at the goal" in ans.text and "mission send" in ans.text and "--reverse" in ans.text
    assert core.control.phase == "finished"
    back = mission_tool.reversed_spec(load_mission_spec())
    assert back.path[0] == load_mission_spec().path[-1] and back.path[-1] == load_mission_spec().path[0]
    core.request(M.MissionRequest(stamp=now, action="send", spec=back, source="test"), now)
    ans = core.request(M.MissionRequest(stamp=now, action="start", source="test"), now)
    assert ans.accepted and core.control.phase == "running", ans


def test_a_restarted_station_shows_its_missions_phase_and_progress() -> None:
    spec = spec_of(load_mission())
    c = MissionControl("r1", spec)
    c.request(M.MissionRequest(stamp=0.0, action="start"), Fitness(""), 0.0)
    c.progress = 0.37
    assert c.unsaved
    back = MissionControl.restored("r1", M.decode(M.encode(c.saved()), type(c.saved())))
    assert (back.phase, round(back.progress, 2)) == ("paused", 0.37) and "station restarted" in back.reason
    c.reached()
    back = MissionControl.restored("r1", c.saved())
    assert (back.phase, back.progress) == ("finished", 1.0)
    assert back.answer(0.0, True, "").progress == 1.0


# -------------------------------------------------------------------------------------------- scmbridge status
def _seen(statuses: dict[tuple[str, str], M.Status]):
    from bridge.tools.status import Seen

    seen = Seen()
    now = time.monotonic()
    seen.latest = {k: (st, now) for k, st in statuses.items()}
    return seen


def test_status_says_an_estop_is_not_ok_at_the_goal_names_a_missing_driver_and_shows_parked() -> None:
    parked = M.Status(stamp=0.0, seq=1, node="station", ok=True, state="parked", reason="goal_reached",
                      text="goal reached", progress=1.0)
    fit = FIT
    estop = M.Status(stamp=0.0, seq=1, node="driver", ok=False, state="estop", reason="estop",
                     text="link can: estop latched by operator")
    now = time.monotonic()
    assert robot_ok({"station": (parked, now), "driver": (fit, now)}, now)
    assert not robot_ok({"station": (parked, now), "driver": (estop, now)}, now)
    lines, ok = status_report(_seen({("r1", "station"): parked, ("r1", "driver"): fit}), ["r1"])
    assert ok and [ln.split()[:3] for ln in lines] == [["r1", "station", "parked"], ["r1", "driver", "parked"]]
    lines, ok = status_report(_seen({("r1", "station"): parked, ("r1", "driver"): estop}), ["r1"])
    assert not ok
    lines, ok = status_report(_seen({("r1", "station"): parked}), ["r1"])
    assert not ok and any(ln.split()[:3] == ["r1", "driver", "missing"] for ln in lines), lines


def test_status_exits_1_for_an_estopped_robot_whose_mission_is_finished_over_zenoh() -> None:
    """The command itself, over real Zenoh: docs/CLI.md's exit status (0 driving or parked, 1 otherwise)."""
    port = free_port()
    parked = M.Status(stamp=0.0, seq=0, node="station", ok=True, state="parked", reason="goal_reached",
                      text="goal reached", progress=1.0)
    estop = M.Status(stamp=0.0, seq=0, node="driver", ok=False, state="estop", reason="estop",
                     text="link can: estop latched by operator")
    stop = threading.Event()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session:
        pubs = {n: session.declare_publisher(M.status_key("r9", n)) for n in ("station", "driver")}

        def publish() -> None:
            seq = 0
            while not stop.is_set():
                for n, st in (("station", parked), ("driver", estop)):
                    pubs[n].put(M.encode(M.Status(**{**{f: getattr(st, f) for f in st.__struct_fields__},
                                                     "stamp": time.monotonic(), "seq": seq})))
                seq += 1
                stop.wait(0.2)

        t = threading.Thread(target=publish, daemon=True)
        t.start()
        try:
            res = subprocess.run([sys.executable, "-m", "bridge", "status", "--all", "--mode", "client", "--connect",
                                  tcp(port), "--timeout", "1.0"], capture_output=True, text=True, timeout=60)
        finally:
            stop.set()
            t.join(2)
    assert res.returncode == 1 and "estop latched by operator" in res.stdout, res.stdout + res.stderr


# ------------------------------------------------------------------------------------- real nodes, back to back
def _ask_engage(session, robot: str, engaged: bool = True) -> M.EngageState:
    (ans,) = engage_tool.ask(session, robot, M.EngageRequest(stamp=time.monotonic(), engaged=engaged,
                                                             source="operator"), 20.0)
    return ans


def _ask_mission(session, robot: str, action: str) -> M.MissionState:
    ans = mission_tool.ask(session, robot, M.MissionRequest(stamp=time.monotonic(), action=action,
                                                            source="operator"), 5.0)
    assert ans is not None, f"no station answered {action}"
    return ans


def _estop(session, robot: str, engaged: bool) -> None:
    def msg(to) -> M.Estop:  # as the person's tool sends it: addressed, fresh, with its nonce (bridge/core/acts.py)
        return stamped(M.Estop(stamp=time.monotonic(), engaged=engaged, source="operator", reason="test"), to)

    answers = confirm(session, [robot], msg, engaged, time.monotonic() + 10.0)
    assert answers[robot] and all(st.latched == engaged for st in answers[robot].values()), answers


@pytest.mark.timeout(240)
def test_a_request_right_after_an_engage_or_a_release_is_accepted_and_status_says_the_next_step(tmp_path) -> None:
    port, robot = free_port(), f"op{os.getpid()}"
    x0 = ",".join(f"{a:.6f}" for a in load_mission().start)
    client = ["--robot", robot, "--mode", "client", "--connect", tcp(port)]
    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
        col = Collector(session)
        status = col.listen(M.status_key(robot, "station"), M.Status)
        drv = col.listen(M.status_key(robot, "driver"), M.Status)
        kids.spawn(["driver", "--link", "can", "--emulate", "--x0", x0, *client, "--duration", "200"],
                   out=subprocess.DEVNULL)
        kids.spawn(["station", *client, "--store", str(tmp_path / "p.bin"), "--duration", "200"],
                   out=subprocess.DEVNULL)
        assert col.wait(lambda: status and status[-1].state == "idle" and drv and drv[-1].state == "waiting", 90)
        assert drv[-1].host and drv[-1].host == status[-1].host  # one machine, one boot: said by both

        # engage, then start at once: it drives
        assert _ask_engage(session, robot).engaged
        ans = _ask_mission(session, robot, "start")
        assert ans.accepted, ans
        assert col.wait(lambda: status[-1].state == "driving", 30), status[-1].text

        # disengaged: the mission pauses; engage and at once resume: accepted (it was refused "waiting for engage")
        assert not _ask_engage(session, robot, engaged=False).engaged
        assert col.wait(lambda: status[-1].state == "paused", 10), status[-1].text
        assert _ask_engage(session, robot).engaged
        ans = _ask_mission(session, robot, "resume")
        assert ans.accepted and "resumed" in ans.text, ans
        assert col.wait(lambda: status[-1].state == "driving", 10), status[-1].text

        # an estop pauses it; release and at once start: accepted (it was refused "estop latched by operator")
        _estop(session, robot, True)
        assert col.wait(lambda: status[-1].state == "paused" and "estop latched" in status[-1].text, 10)
        _estop(session, robot, False)
        ans = _ask_mission(session, robot, "start")
        assert ans.accepted, ans
        assert col.wait(lambda: status[-1].state == "driving", 10), status[-1].text

        # released but not resumed: the station says so at once, with the command to type, and no estop any more
        _estop(session, robot, True)
        assert col.wait(lambda: status[-1].state == "paused" and "estop latched" in status[-1].text, 10)
        t_rel = time.monotonic()
        _estop(session, robot, False)
        assert col.wait(lambda: f"scmbridge mission resume --robot {robot}" in status[-1].text, 1.5), \
            status[-1].text
        assert time.monotonic() - t_rel < 1.0 and "estop" not in status[-1].text, status[-1].text
        # `status` prints the driver host's last status too: wait until the host has said it was released (on a
        # loaded machine its status after the release can come after the station's, and the CLI would read the one
        # before)
        assert col.wait(lambda: drv and "estop" not in drv[-1].text, 10), drv[-1].text
        res = subprocess.run([sys.executable, "-m", "bridge", "status", *client],
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 1 and "mission resume --robot" in res.stdout and "estop" not in res.stdout, res.stdout

        # the same as a person types it: the release and the resume chained, no pause between them
        _estop(session, robot, True)
        assert col.wait(lambda: status[-1].state == "paused" and "estop latched" in status[-1].text, 10)
        z = f"--mode client --connect {tcp(port)}"
        scm = f"{sys.executable} -m bridge"
        chained = subprocess.run(f"{scm} estop --robot {robot} --release {z} && {scm} mission resume --robot "
                                 f"{robot} {z}", shell=True, capture_output=True, text=True, timeout=90)
        assert chained.returncode == 0 and "resumed" in chained.stdout, chained.stdout + chained.stderr

        # docs/OPERATING.md's way back from the goal, as written (this robot's name, this router's endpoint)
        from tests.repo.test_docs_commands import documented

        ops = [(n, a) for d, n, a in documented() if d == "docs/OPERATING.md" and n.startswith("mission ")]
        i = next(i for i, (n, a) in enumerate(ops) if n == "mission send" and "--reverse" in a)
        back = ops[i:i + 2]  # the reversed mission and the start after it (the first day's placing is another)
        assert [n for n, _ in back] == ["mission send", "mission start"], ops
        for name, args in back:
            res = subprocess.run([sys.executable, "-m", "bridge", *name.split(),
                                  *[robot if a == "rover1" else a for a in args], "--mode", "client", "--connect",
                                  tcp(port)], capture_output=True, text=True, timeout=60)
            assert res.returncode == 0, (name, res.stdout + res.stderr)
        assert "paper-s-path-reversed" in res.stdout and "started" in res.stdout, res.stdout


@pytest.mark.timeout(120)
def test_a_never_engaged_mavlink_host_does_not_say_the_operator_took_a_vehicle_found_in_manual(tmp_path) -> None:
    from sim_learner.dynamics import mpc_learner
    from sim_learner.mavlink_rover import MavlinkRover
    from sim_learner.vehicle import SimVehicle

    rover = MavlinkRover(SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic()), init_s=0.2,
                         ekf_position_s=0.4).start()
    port, robot = free_port(), f"mm{os.getpid()}"
    cfg = tmp_path / "driver.toml"
    cfg.write_text(f'[link.mavlink]\nurl = "udpout:127.0.0.1:{rover.port}"\nrate_hz = 20\n')
    try:
        with open_session(make_config(mode="router", listen=[tcp(port)])) as session, Children() as kids:
            col = Collector(session)
            drv = col.listen(M.status_key(robot, "driver"), M.Status)
            host = kids.spawn(["driver", "--link", "mavlink", "--config", str(cfg), "--robot", robot, "--mode",
                               "client", "--connect", tcp(port), "--duration", "60"])
            assert col.wait(lambda: drv and drv[-1].state == "waiting" and "MANUAL" in drv[-1].text, 60), \
                [s.text for s in drv[-2:]] + [kids.said()]
            assert rover.mode_name == "MANUAL"
            text = drv[-1].text
            os.killpg(host.pid, 2)
            host.wait(timeout=20)
            said = kids.said()
        assert "operator took control" not in text and "waiting for the operator: mode MANUAL" in text, text
        assert "operator took control" not in said and "MANUAL" in said, said
    finally:
        rover.stop()


def test_the_qpoases_banner_is_never_printed() -> None:
    """Findings: qpOASES printed its licence banner twice per robot (the solver, then its buffer, each make a memory),
    whatever ``printLevel`` says; then once at every station start. No third-party banner in a service's log."""
    code = ("from bridge.teacher.codegen import build_mpc\nfrom transfer.teacher.mpc import MpcConfig\n"
            "for _ in range(3):\n    build_mpc(MpcConfig(N=10, dt=0.1, solver='rti-qpoases'))\nprint('built')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout == "built\n", res.stdout + res.stderr
    assert "qpOASES" not in res.stderr and "Lesser General Public License" not in res.stderr, res.stderr


def test_the_learned_hull_encloses_every_refined_pair() -> None:
    """Finding: of the boundary pairs alone, a run that met only the learner's top speed had a sliver of a hull (the
    pairs plot's dashed envelope) that left out nearly every refined pair."""
    import numpy as np

    from transfer.domain import Bounds
    from transfer.store import PairStore

    rng = np.random.default_rng(1)
    learner, teacher = Bounds((0.0, 0.5), (-0.5, 0.5)), Bounds((0.0, 1.0), (-1.0, 1.0))
    store = PairStore(learner, teacher, k_min=3)
    for _ in range(3000):
        u = learner.denormalise(rng.uniform(0, 1, 2))
        if rng.random() < 0.1:
            u[0] = 0.5  # the top speed: the only boundary it meets
        store.add([1.5 * u[0] + 0.05 * rng.normal(), 1.2 * u[1] * (1 - 0.5 * u[0]) + 0.02 * rng.normal()], u)
    refined = np.array([p.u_T for p in store.refined()])
    assert len(refined) > 100
    assert np.all(store.limits.contains(refined, use_hull=True, tol=1e-6))
    again = PairStore.from_bytes(store.to_bytes())  # a reloaded store draws the same hull
    np.testing.assert_allclose(again.limits.hull, store.limits.hull)


def test_the_missing_extra_hint_names_an_install_that_brings_the_package() -> None:
    """Finding: a robot install's `station --help` said `pip install --no-deps ... '.[station]'`, which installs no
    package of the extra. The hint's lock pins every package an extra's command needs."""
    from pathlib import Path

    from bridge.tools.cli import EXTRA_OF, FULL_INSTALL

    lock_name = FULL_INSTALL.split("-r ", 1)[1].split()[0]
    lock = (Path(__file__).resolve().parents[2] / lock_name).read_text()
    dists = {"foxglove": "foxglove-sdk"}
    for module in EXTRA_OF:
        assert f"\n{dists.get(module, module)}==" in lock, module
    assert "--no-deps" in FULL_INSTALL and "'.[" not in FULL_INSTALL


def test_the_demo_line_counts_every_method() -> None:
    from bridge.tools.demo import method_counts

    counters = {"method_scm": 3, "method_barycentric": 40, "method_affine": 2, "method_direct": 1,
                "method_perturb": 0, "method_stop": 5, "refined_pairs": 9}
    line = method_counts(counters)
    shown = dict(w.split("=") for w in line.split())
    assert sum(int(v) for v in shown.values()) == 51 and shown["barycentric"] == "40" and "affine" in shown, line


# ---------------------------------------------------------------------------------------------------- report
class _Entry:
    """A recorded message as the report reads it (its key, its receive time, its decoded message)."""

    def __init__(self, topic: str, log_time: int, msg) -> None:
        self.topic, self.log_time, self.msg = topic, log_time, msg

    def message(self):
        return self.msg


def test_the_report_counts_driving_apart_from_an_estop_and_says_same_machine_from_the_statuses() -> None:
    """Finding: `time_s` 54.1 s held a 14 s estop, and the report said "different machines" for one machine."""
    from bridge.core.config import mission_from_spec
    from bridge.tools.demo import Monitor
    from bridge.tools.report import FeedSession, command_latency, machines

    mission = mission_from_spec(M.MissionSpec(name="line", path=[[0.0, 0.0], [0.8, 0.0]], goal_tolerance=0.05))
    feed, k = FeedSession(), M.Keys("r1")
    mon = Monitor(feed, "r1")
    t, x = 100.0, 0.0
    for step in range(160):  # 8 s at 20 Hz: 2 s driving, a 2 s estop, 2 s driving to the goal, parked 2 s
        t += 0.05
        moving = step * 0.05 < 2.0 or 4.0 <= step * 0.05 < 6.0
        x = min(0.8, x + 0.01) if moving else x
        reason = "cmd" if moving else ("estop" if step * 0.05 < 4.0 else "stop")
        feed.put(k.applied, M.encode(M.Applied(stamp=t, seq=step, v=0.2 if moving else 0.0, omega=0.0,
                                               reason=reason, cmd_seq=step)))
        feed.put(k.state, M.encode(M.LearnerState(stamp=t, seq=step, x=x, y=0.0, theta=0.0)))
    feed.put(M.status_key("r1", "station"), M.encode(M.Status(stamp=t, seq=1, node="station",
                                                              counters={"goal_reached": 1})))
    s = mon.summary(mission)
    assert 5.6 <= s["time_s"] <= 5.9 and 3.6 <= s["driving_s"] <= 3.9 and 1.9 <= s["paused_s"] <= 2.1, s

    def status(node: str, host: str | None) -> _Entry:
        return _Entry(M.status_key("r1", node), 1, M.Status(stamp=1.0, seq=1, node=node, host=host))

    cmd = _Entry(k.cmd, 10, M.Command(stamp=5.0, seq=7, v=0.1, omega=0.0, method="scm"))
    applied = _Entry(k.applied, 12, M.Applied(stamp=5.002, seq=1, v=0.1, omega=0.0, reason="cmd", cmd_seq=7))
    one = [status("station", "lab/abc"), status("driver", "lab/abc"), cmd, applied]
    two = [status("station", "lab/abc"), status("driver", "robot/def"), cmd, applied]
    old = [status("station", None), status("driver", None), cmd, applied]
    assert machines(one, "r1")["same"] is True and machines(two, "r1")["same"] is False
    assert machines(old, "r1")["same"] is None
    assert command_latency(one, "r1", True)[0]["stamps_one_clock"]
    assert not command_latency(two, "r1", False)[0]["stamps_one_clock"]
    assert command_latency(old, "r1", None)[0]["stamps_one_clock"]  # old nodes: judged from the numbers
