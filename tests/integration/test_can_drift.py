"""A learner that changes, on the CAN link (docs/PAPER.md, "Beyond the paper"): the emulated ODrive controllers
change at run time as scheduled (``--drift``: a sagging battery lowers the motors' top speed, a dragging wheel yaws
the robot; ``sim_learner.can_ecu.Drift``), and the whole HIL loop (``scmbridge demo``: station, driver host with the
controllers on its virtual CAN bus, Zenoh on 127.0.0.1) drives through a battery sag with the station's change
detection on: it re-learns the cells that no longer hold, names them, and reaches the goal. Every process started
here is stopped; every wait is bounded."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import uuid
from importlib import resources
from pathlib import Path

import can
import numpy as np
import pytest
import tomllib

from bridge.nodes.station_tags import read_store
from bridge.tools.procs import Children
from drivers.can.config import CanLinkConfig
from sim_learner.can_ecu import DRIFT_AMOUNT, DiffDriveEcus, Drift
from sim_learner.dynamics import mpc_learner
from sim_learner.vehicle import SimVehicle
from tests.wait import until
from transfer.pairs import teacher_equivalent
from transfer.store import PairStore


def test_a_drift_is_parsed_with_its_defaults_and_a_mistake_is_named() -> None:
    assert Drift.parse("battery") == Drift("battery", 20.0, 10.0, DRIFT_AMOUNT["battery"])
    assert Drift.parse("wheel:5:0:0.2") == Drift("wheel", 5.0, 0.0, 0.2)
    for bad in ("sag", "battery:x", "battery:1:2:1.5", "wheel:-1", "battery:1:2:0.1:9"):
        with pytest.raises(ValueError, match="--drift"):
            Drift.parse(bad)
    d = Drift("battery", 10.0, 4.0, 0.3)
    assert [d.share(t) for t in (0.0, 10.0, 12.0, 14.0, 99.0)] == [0.0, 0.0, 0.5, 1.0, 1.0]
    assert Drift("wheel", 3.0, 0.0, 0.1).share(3.0) == 1.0


def _drive(drift: Drift, times: list[float], v: float = 0.3) -> list[tuple[float, float]]:
    """Raw CANSimple frames from a master on a virtual bus: both axes in closed-loop velocity control, the wheels
    fed a straight ``v`` (m/s) at each of ``times`` on the controllers' own (here a test's) clock; the body command
    the vehicle got after each feed."""
    clock = [0.0]
    channel = f"drift-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=0.0)
    master = can.Bus(interface="virtual", channel=channel)
    got = []
    ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, drift=drift, clock=lambda: clock[0])
    turns = v / (2.0 * math.pi * ecus.radius)

    def tx(node: int, cmd: int, data: bytes) -> None:
        master.send(can.Message(arbitration_id=(node << 5) | cmd, data=data, is_extended_id=False))

    def settle(pred) -> None:
        assert until(pred, 20.0, 0.005), "the controllers did not take the frames within 20 s"

    with ecus:
        try:
            for node in (0, 1):
                tx(node, 0x0B, struct.pack("<II", 2, 1))  # velocity control, passthrough
                tx(node, 0x07, struct.pack("<I", 8))  # closed loop
            settle(lambda: ecus.axis(0).state == 8 and ecus.axis(1).state == 8 and ecus.axis(1).control_mode == 2)
            for k, t in enumerate(times):
                clock[0] = t
                speed = turns * (1.0 + 1e-6 * k)  # a new value each time: the test sees when it was taken
                tx(0, 0x0D, struct.pack("<ff", speed, 0.0))
                tx(1, 0x0D, struct.pack("<ff", -speed, 0.0))
                settle(lambda s=speed: ecus.axis(0).input_vel == pytest.approx(s, rel=1e-7)
                       and ecus.axis(1).input_vel == pytest.approx(-s, rel=1e-7))
                settle(lambda: vehicle.t >= clock[0])
                got.append(vehicle.cmd)
        finally:
            master.shutdown()
    return got


def test_a_sagging_battery_lowers_the_top_speed_the_wheels_reach_from_when_they_first_turned() -> None:
    m = mpc_learner()
    top = m.v_range[1] + max(abs(m.w_range[0]), abs(m.w_range[1])) * 0.4 / 2  # the fastest command's wheel speed
    got = _drive(Drift("battery", 1.0, 2.0, 0.3), [5.0, 5.5, 7.0, 9.0])  # the wheels first turn at 5 s
    assert [g[0] for g in got[:2]] == pytest.approx([0.3, 0.3], rel=1e-5)  # before the change: what was asked
    assert got[2][0] == pytest.approx(0.85 * top, rel=1e-5) and 0.85 * top < 0.3  # halfway through the sag
    assert got[3][0] == pytest.approx(0.7 * top, rel=1e-5) and got[3][1] == pytest.approx(0.0, abs=1e-9)


def test_a_dragging_left_wheel_yaws_the_robot_left() -> None:
    got = _drive(Drift("wheel", 0.0, 0.0, 0.1), [1.0, 2.0])
    for v, omega in got:
        assert v == pytest.approx(0.3 * 0.95, rel=1e-5) and omega == pytest.approx(0.03 / 0.4, rel=1e-4)


#: where the drift tests' mission ends (m along x): the paper's S-path to just past its second bend's apex (7.2 of
#: its 9.6 m), from its own start. The changes come 15-18 s after the wheels first turn, past the first bend, on the
#: straight between the bends; the goal comes well after the changes have ended, before the end of the whole path.
MISSION_TO_X = 6.0

#: the sagging battery of the battery test: ``--drift`` KIND:AT (the default ramp and amount), AT s after the wheels
#: first turn (that test's docstring says why there)
BATTERY_SAG = "battery:18"


def _mission(tmp_path: Path) -> Path:
    """The paper's S-path (the shipped mission ``paper-s-path``) up to ``MISSION_TO_X``, its obstacles and start, as
    a mission file: the goal is its last waypoint kept."""
    text = resources.files("bridge").joinpath("missions", "paper_s_path.toml").read_text()
    d = tomllib.loads(text)
    path = [p for p in d["path"] if p[0] <= MISSION_TO_X]
    obstacles = [o for o in d["obstacles"] if o[0] - o[2] <= MISSION_TO_X]
    f = tmp_path / "mission.toml"
    f.write_text("\n".join([f'name = "paper-s-path-to-{MISSION_TO_X:g}"', f'frame = "{d["frame"]}"',
                            f"goal_tolerance = {d['goal_tolerance']}", f"start = {d['start']}",
                            f"obstacles = {obstacles}", f"path = {path}", ""]))
    return f


def _demo(tmp_path: Path, drift: str, duration: float, timeout: float) -> tuple[dict, PairStore, str]:
    """``scmbridge demo --link can --drift DRIFT`` (the station with ``[transfer] adapt``) on the S-path up to
    ``MISSION_TO_X`` (:func:`_mission`) run to its end: its summary, its saved pair store and the station's log; the
    demo must have reached the goal and re-learned cells, and its summary, log and saved store agree on them (the
    cells named, how many re-learnings, when: the station's wall clock)."""
    out = tmp_path / "demo"
    with Children() as kids:
        demo = kids.spawn(["demo", "--link", "can", "--mission", str(_mission(tmp_path)), "--drift", drift,
                           "--duration", str(duration), "--out", str(out)], subprocess.PIPE)
        try:
            stdout, _ = demo.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the demo did not end within {timeout} s")
    lines = [ln for ln in stdout.decode().splitlines() if ln.startswith("summary: ")]
    assert demo.returncode == 0 and lines, stdout.decode()[-3000:]
    summary = json.loads(lines[0][len("summary: "):])
    assert summary["reached_goal"], summary
    assert summary["cells_relearned"] > 0 and summary["changed_cells"], summary
    store = read_store(out / "pairs.bin")
    assert store.adapt and store.relearned >= summary["cells_relearned"]
    changed = {c.id for c in store.changed_cells()}
    assert set(summary["changed_cells"]) <= changed
    assert all(c.at is not None and c.at > 1e9 for c in store.changed_cells())  # when: the station's wall clock
    log = (out / "station.log").read_text()
    assert log.count("re-learned: its learner no longer answers") == store.relearned
    return summary, store, log


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_hil_loop_relearns_the_cells_a_sagging_battery_changed_and_reaches_the_goal(tmp_path: Path) -> None:
    """``scmbridge demo --link can --drift battery:18`` (:data:`BATTERY_SAG`): the motors' top speed falls 30 % over
    10 s, from 18 s after the wheels first turn (from no pairs: the first bend's cells are learned by then), on the
    S-path to just past its second bend (:func:`_mission`); the station runs with ``[transfer] adapt``. The demo's
    summary, the station's log and its saved store agree on the cells re-learned.

    Where the sag falls is what the claim needs. The cells it changes are those driven near the top speed, and a cell
    shows a change only against pairs it took before it: the cells of the straight between the two bends, learned
    there before the sag and driven there during it. The sag starts so that its first re-learning falls in the
    middle of that straight, not at its end: a loaded machine brings the pairs that show the change later, and the
    robot's place when the sag comes shifts with its start. A sag whose change is first seen at the straight's end
    meets the second bend's cells, driven only once before at the top speed (too few pairs to test), and the learned
    top speed, re-learned from the boundary pairs meanwhile, then keeps the teacher below the top speed: nothing or
    only a cell of the last approach is re-learned. Much earlier, the robot under the sag hit an obstacle on its way,
    which is not what this test is about."""
    _demo(tmp_path, BATTERY_SAG, 170, 280)  # (a deadline: the demo ends at the goal; its start-up counts in it)


def _response(u_L: np.ndarray, drag: float = 0.0) -> np.ndarray:
    """What the emulated learner does with the body command ``u_L`` over one tick, as the teacher's command that
    would do the same (f_T^-1, the pair's teacher part), with its left wheel's speed cut by ``drag`` (a share: the
    emulated controllers' ``wheel`` drift, at the driver's track width)."""
    v, w = float(u_L[0]), float(u_L[1])
    half = CanLinkConfig().track_width / 2.0
    left, right = (1.0 - drag) * (v - w * half), v + w * half
    body = np.array([0.5 * (left + right), (right - left) / (2.0 * half)])
    x0 = np.zeros(3)
    return teacher_equivalent(x0, mpc_learner().step(x0, body, 0.1), 0.1)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_the_hil_loop_relearns_the_cells_a_dragging_wheel_changed_in_the_direction_of_the_drag(tmp_path: Path) -> None:
    """``scmbridge demo --link can --drift wheel:15:0``: from 15 s after the wheels first turn (the S-path's first
    bend learned by then, its right bends still to come) the left wheel reaches 10 % less than it is driven at, at
    once (``:0``: a step; the default 10 s ramp let a cell driven only during the ramp be re-learned from a part of
    the drag, while this test compares with all of it), so
    the robot yaws left and slows; the station runs with ``[transfer] adapt``. What a controls engineer checks: the
    goal reached without a collision; the cells re-learned named alike by the summary, the log and the saved store;
    and each re-learned cell's refined pair moved from what its learner command did before the change towards what
    the dragging wheel makes of it (the emulator's model, :func:`_response`), in the drag's direction by at least a
    third of its effect. Where the drag yaws the command, its teacher part turns left by at least a third of what the
    drag adds: the map now asks the learner for a command turning further right (an opposite omega offset) for the
    same teacher command. Measured on the 9 cells re-learned in 3 runs: 99-143 % of the drag's effect (with the
    ramp, the cells the slowing MPC drives during it: 34-62 %). The mission is the S-path to just past its second
    bend's apex (:func:`_mission`): about 45 s of driving (the whole path: 52).

    What does not hold, and is not asserted (docs/PAPER.md, "Beyond the paper"): the learner cannot follow a right
    turn after the change (at its right-most command it turns an eighth to a quarter as fast as before, whatever the
    map), and the learned right-turn limit follows it down only where pairs come at that command after the change."""
    summary, store, _ = _demo(tmp_path, "wheel:15:0", 170, 230)  # (a deadline: it ends at the goal)
    assert summary["collided"] is False, summary
    refined = {r.id: r for r in store.refined()}
    relearned = [refined[c.id] for c in store.changed_cells() if c.id in refined]
    assert relearned, (store.changed_cells(), sorted(refined))
    yawed = 0
    for r in relearned:
        before, after = _response(r.u_L), _response(r.u_L, DRIFT_AMOUNT["wheel"])
        wanted, moved = after - before, r.u_T - before  # what the drag did to this command; what the store learned
        assert float(moved @ wanted) >= float(wanted @ wanted) / 3.0 > 0.0, (r, before, after)
        if wanted[1] > 0.01:  # the drag yaws this command left (not where the command's turn is clipped)
            assert moved[1] >= wanted[1] / 3.0, (r, before, after)
            yawed += 1
    assert yawed, [(r.id, r.u_L) for r in relearned]  # and the re-learned cells include one the drag yaws
