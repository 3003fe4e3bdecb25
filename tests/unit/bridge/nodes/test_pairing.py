"""What the station learns from is checked before it is paired: forged or garbled telemetry is counted and dropped,
never learned, and never stops learning (the pairer, pure: times are arguments).

Findings this answers: one forged ``state`` stamped 1e11 stopped pairing for good (0 pairs in 20 s); forged
``state`` + ``applied`` put a pair with teacher v = 121 m/s in the persisted store; 20 spoofed states 30 m away
put a teacher v = 14.6 m/s pair there."""

from __future__ import annotations

import numpy as np

from bridge.nodes.pairing import IntervalPairer
from transfer.domain import Bounds
from transfer.paper import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
from transfer.teacher.unicycle import step

TB = Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
LB = Bounds(MPC_LEARNER_V, MPC_LEARNER_W)


def _pairer() -> IntervalPairer:
    vmax, wmax = float(np.max(np.abs(LB.v))), float(np.max(np.abs(LB.w)))
    return IntervalPairer(0.1, max_speed=2 * vmax, max_turn=2 * wmax, command_bounds=LB, teacher_bounds=TB)


def _drive(p: IntervalPairer, t0: float, x: np.ndarray, u: np.ndarray, n: int, lag: float = 0.003,
           inject=None, echo: np.ndarray | None = None) -> tuple[list, float, np.ndarray]:
    """``n`` poses every 20 ms under command ``u``, its echo (``echo`` if given) every 100 ms as the driver host
    sends it, each received ``lag`` s after its stamp; ``inject(i, t)`` may feed forged events between them."""
    pairs = []
    t = t0
    said = u if echo is None else echo
    for i in range(n):
        if i % 5 == 0:
            out = p.applied(t, *said, "cmd", received=t + lag)
            if out:
                pairs.append(out)
        t += 0.02
        x = step(x, u, 0.02)
        if inject is not None:
            inject(i, t)
        out = p.state(t, x, received=t + lag)
        if out:
            pairs.append(out)
    return pairs, t, x


def test_one_forged_far_future_stamp_does_not_stop_pairing() -> None:
    p = _pairer()
    u = np.array([0.2, 0.05])

    def forge(i: int, t: float) -> None:
        if i == 10:
            p.state(1e11, np.array([5.0, 5.0, 0.0]), received=t + 0.003)

    pairs, t, x = _drive(p, 0.0, np.zeros(3), u, 100, inject=forge)
    assert p.implausible_stamp == 1 and len(pairs) >= 15
    assert all(np.allclose(ul, u) and np.allclose(ut, u, atol=0.01) for ut, ul in pairs)


def test_a_forged_first_event_is_left_behind_after_a_few_real_ones() -> None:
    p = _pairer()
    p.state(1e11, np.zeros(3), received=0.0)  # the very first event ever is forged: nothing to judge it by
    pairs, _, _ = _drive(p, 0.0, np.zeros(3), np.array([0.2, 0.0]), 100)
    assert p.resyncs == 1 and len(pairs) >= 15


def test_spoofed_poses_far_away_are_never_paired() -> None:
    p = _pairer()
    u = np.array([0.25, 0.0])

    def spoof(i: int, t: float) -> None:
        if i % 5 == 2:  # interleaved with the real telemetry, 30 m away
            p.state(t + 0.001, np.array([30.0, 0.0, 0.0]), received=t + 0.004)

    pairs, _, _ = _drive(p, 0.0, np.zeros(3), u, 150, inject=spoof)
    assert p.implausible_pose >= 25 and len(pairs) >= 20
    assert all(abs(ut[0]) < 0.35 for ut, _ in pairs), [ut for ut, _ in pairs]


def test_a_relocated_robot_is_followed_and_no_pair_spans_the_jump() -> None:
    p = _pairer()
    u = np.array([0.2, 0.0])
    pairs, t, x = _drive(p, 0.0, np.zeros(3), u, 30)
    more, _, _ = _drive(p, t + 0.01, x + np.array([3.0, 0.0, 0.0]), u, 60)  # mocap re-zeroed: 3 m at once
    assert p.resyncs == 1 and len(more) >= 8
    assert all(np.allclose(ut, u, atol=0.01) for ut, _ in pairs + more)


def test_a_forged_applied_echo_beyond_the_vehicles_box_is_never_paired() -> None:
    p = _pairer()
    pairs, _, _ = _drive(p, 0.0, np.zeros(3), np.array([0.2, 0.0]), 40, echo=np.array([121.0, 0.0]))
    assert pairs == [] and p.implausible_pair >= 1


def test_a_store_with_a_pair_no_vehicle_could_make_is_quarantined_not_served(tmp_path) -> None:
    """Finding: a learned pair with teacher v = 121 m/s was persisted; afterwards the station's pairs reply broke the
    wire contract and `pairs show --robot` exited 2 on every restart."""
    from bridge.core.paths import save_atomic
    from bridge.nodes.station_core import load_store
    from transfer.store import PairStore

    poisoned = PairStore(LB, TB, k_min=1)
    poisoned.add([121.0, 0.0], [0.2, 0.0])
    poisoned.add([0.2, 0.1], [0.2, 0.1])
    f = tmp_path / "pairs.bin"
    save_atomic(f, poisoned.to_bytes())
    store, how = load_store(f, LB, TB, (11, 11), 1)
    assert how == "new pair store" and store.raw_count == 0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("pairs.bin.corrupt-")]


def test_another_sender_on_the_robots_commands_or_implausible_telemetry_make_the_station_not_ok(tmp_path) -> None:
    """Finding: `ok` stayed true with two stations publishing for one robot, and while pairing was halted."""
    from bridge.core import wire as M
    from bridge.core.config import StationConfig, load_mission
    from bridge.nodes.station_core import StationCore
    from bridge.nodes.station_status import INTEGRITY_WINDOW_S

    st = StationCore(StationConfig(), "r1", 10.0, tmp_path / "p.bin", load_mission())
    st.verdict.why, st.verdict.reason = "driving", "ok"  # as after a tick that drove
    assert st.status(1.0).ok
    st.heard_command(M.Command(stamp=1.0, seq=1, v=0.1, omega=0.0, method="scm", epoch=st.outbox.epoch), 1.0)
    assert st.status(1.1).ok  # its own command, heard back
    st.heard_command(M.Command(stamp=1.0, seq=1, v=0.1, omega=0.0, method="scm", epoch=st.outbox.epoch ^ 1), 1.2)
    s = st.status(1.3)
    assert not s.ok and "another sender publishes commands" in s.text
    assert st.status(1.2 + INTEGRITY_WINDOW_S + 0.1).ok
    st.pairer.state(0.0, np.zeros(3), received=100.0)
    st.pairer.state(1e11, np.zeros(3), received=100.01)  # a forged stamp, dropped
    s = st.status(100.1)
    assert not s.ok and "implausible telemetry" in s.text and s.counters["implausible_stamps"] == 1


def test_a_pose_measured_before_an_echo_but_received_after_it_still_pairs() -> None:
    """Finding (the MAVLink pairing bench beside two busy loops, 2 runs of 12): a pose the vehicle measured just before
    a command was sent reached the station after that command's echo; fed as it came it was older than an event
    already used, dropped as out of order, and a third of the commands formed no pair. Through :class:`Reorder`
    every such pose takes its place."""
    from bridge.nodes.pairing import Reorder

    def run(reorder: Reorder | None) -> tuple[IntervalPairer, list]:
        p, pairs, x, t = _pairer(), [], np.zeros(3), 0.0
        arrivals: list[tuple[float, int, float, object]] = []  # (received, kind, stamp, payload)
        for k in range(60):  # a command every 0.1 s, poses every 20 ms; the last three of each are 70 ms late
            u = np.array([0.15 + 0.05 * (k % 3), 0.1 * ((k % 5) - 2)])
            arrivals.append((t, 0, t, u))
            for i in range(5):
                x = step(x, u, 0.02)
                t += 0.02
                arrivals.append((t + (0.07 if i >= 2 else 0.002), 1, t, x.copy()))
        arrivals.sort(key=lambda a: a[0])
        for received, kind, stamp, e in arrivals:
            events = [(stamp, kind, e, received)]
            if reorder is not None:
                reorder.push(stamp, kind, received, (stamp, kind, e, received))
                events = reorder.ready(received)
            for s, kd, ev, r in events:
                out = p.applied(s, *ev, "cmd", received=r) if kd == 0 else p.state(s, ev, received=r)
                if out is not None:
                    pairs.append(out)
        return p, pairs

    raw, raw_pairs = run(None)
    p, pairs = run(Reorder())
    assert raw.out_of_order > 100 and len(raw_pairs) < 0.5 * 60  # what it was
    assert p.out_of_order == 0 and len(pairs) >= 55 and p.implausible_stamp == 0
    assert all(np.allclose(ut, ul, atol=0.01) for ut, ul in pairs)  # the learner model here is the teacher's


def test_a_forged_stamp_holds_the_reorder_buffer_for_at_most_its_window() -> None:
    from bridge.nodes.pairing import Reorder

    r = Reorder(0.2)
    r.push(-1e9, 1, 1.0, "forged, far in the past")
    r.push(float("nan"), 1, 1.0, "nan")
    r.push(1.05, 0, 1.05, "echo")
    r.push(1.02, 1, 1.06, "pose")
    assert r.ready(1.1) == ["nan"] and len(r) == 3  # the old stamp is on top and waits for its own window only
    assert r.ready(1.21) == ["forged, far in the past"]
    assert r.ready(1.27) == ["pose", "echo"] and len(r) == 0  # stamp order, though received the other way round


def test_poses_exactly_the_minimum_span_apart_pair_whatever_the_last_digit_of_their_stamps() -> None:
    """ArduPilot sends its 20 Hz positions from a 50 Hz loop, 40 and 60 ms apart, and the driver host puts each on its
    own clock (its ``time_boot_ms`` plus an offset): inside a 100 ms command two poses 40 ms apart span exactly
    ``min_span`` (0.4 ``dt``), and the sum's float rounding made about half of such spans fall a hair short of it, so
    those intervals were rejected. Every one of them pairs."""
    p = _pairer()
    x, u = np.zeros(3), np.array([0.2, 0.1])
    offset = 10544.958  # the host's clock minus the vehicle's boot time, as it came in a SITL run
    pairs, tried = 0, 0
    for k in range(200):  # a new command every 100 ms; its poses at 30 and 70 ms of the vehicle's clock
        boot = 12.3 + 0.1 * k
        u_k = u * (1.0 + 0.01 * (k % 2))  # commands that change every tick, as an MPC's do
        p.applied(boot + offset, *u_k, "cmd", received=boot + offset + 0.003)
        for t_boot in (round(boot + 0.03, 3), round(boot + 0.07, 3)):
            x = step(x, u_k, 0.04)
            p.state(t_boot + offset, x, received=t_boot + offset + 0.003)
        tried += 1
        pairs = p.formed
    assert tried == 200 and pairs >= 199 and p.rejected == 0, (pairs, p.rejected)
