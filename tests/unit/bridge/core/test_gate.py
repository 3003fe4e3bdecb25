"""The driver host's pure safety logic: sender epochs and sequence numbers, a stop is a stop, the deadman, the
estop latch and who may release it. Each test names the finding it guards against."""

from __future__ import annotations

import math

import msgspec
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.core import wire as M
from bridge.core.gate import CONFLICT_WINDOW_S, CommandGate, Decision, SeqGate
from transfer.domain import Bounds

LIMITS = Bounds((-0.5, 0.5), (-1.0, 1.0))
STATION = 0x5EED


def _cmd(seq: int, v: float, w: float, *, epoch: int = STATION, valid_ms: int = 300, method: str = "scm"):
    return M.Command(stamp=1.0, seq=seq, v=v, omega=w, method=method, valid_ms=valid_ms, epoch=epoch, sender="st")


def test_gate_applies_fresh_commands_clamps_and_trips_the_deadman() -> None:
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    assert g.decide(0.0).reason == "start"
    g.offer(_cmd(1, 0.2, 0.1), 1.0)
    assert g.decide(1.1) == Decision(0.2, 0.1, "cmd", 1)
    g.offer(_cmd(2, 3.0, -5.0), 1.2)
    d = g.decide(1.25)
    assert (d.v, d.omega, d.reason) == (0.5, -1.0, "clamped")
    assert not g.offer(_cmd(2, 0.1, 0.0), 1.3)  # replayed / out of order
    assert g.decide(1.2 + 0.31).reason == "deadman" and g.counters["deadman_trips"] == 1
    g.offer(_cmd(3, 0.1, 0.0, valid_ms=50), 2.0)
    assert g.decide(2.1).reason == "stale"  # older than its validity: never applied


def test_one_forged_huge_seq_does_not_lock_the_station_out() -> None:
    """Finding: Command(seq=2**63-1) made the driver host drop every later legitimate command, forever."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    t = 0.0
    for seq in range(1, 11):
        assert g.offer(_cmd(seq, 0.2, 0.0), t)
        t += 0.1
    assert not g.offer(_cmd(2**63 - 1, 0.4, 0.0), t)  # too far ahead of what the sender could have counted
    assert g.counters["seq_jump"] == 1
    for seq in range(11, 21):
        t += 0.1
        assert g.offer(_cmd(seq, 0.2, 0.0), t), seq
        assert g.decide(t).reason == "cmd"


def test_a_restarted_station_is_followed_at_once_and_old_commands_stay_refused() -> None:
    """Finding: a restarted station counted from 0 and was ignored for as long as it had run before."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    for seq in range(1, 500):
        g.offer(_cmd(seq, 0.2, 0.0), seq * 0.1)
    t = 500 * 0.1 + 1.5  # kill -9, restart: 1.5 s of silence
    assert g.offer(_cmd(0, 0.1, 0.0, epoch=0xBEEF), t)  # new epoch, seq from 0: followed at once
    assert g.decide(t + 0.01) == Decision(0.1, 0.0, "cmd", 0)
    assert not g.offer(_cmd(300, 0.4, 0.0), t + 0.05)  # a command of the old run, replayed: refused
    assert g.counters["old_epoch"] == 1
    assert g.offer(_cmd(1, 0.1, 0.0, epoch=0xBEEF), t + 0.1)


def test_a_second_sender_cannot_take_over_a_live_stream() -> None:
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    g.offer(_cmd(1, 0.2, 0.0), 0.0)
    assert not g.offer(_cmd(1, 0.4, 0.0, epoch=0xBAD), 0.1)
    assert g.counters["foreign_epoch"] == 1
    assert g.offer(_cmd(2, 0.2, 0.0), 0.2)


def test_a_second_or_forged_sender_puts_the_stream_in_conflict_for_health() -> None:
    """Finding: `ok` stayed true with two stations publishing for one robot and during a forged-seq lockout."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    g.offer(_cmd(1, 0.2, 0.0), 0.0)
    assert g.conflict(0.05) is None
    g.offer(_cmd(1, 0.4, 0.0, epoch=0xBAD), 0.1)
    assert "second sender" in g.conflict(0.2)
    assert g.conflict(0.1 + CONFLICT_WINDOW_S + 0.01) is None  # it went away: trusted again
    g.offer(_cmd(2 + 10_000, 0.4, 0.0), 3.0)  # a forged seq jump inside the epoch
    assert "seq_jump" in g.conflict(3.1)


def test_two_senders_on_one_epoch_stop_the_vehicle_until_one_is_silent() -> None:
    """Finding (issue 31): a forged command at seq + 1 right after each real one (the station's epoch copied) was
    applied on 341 of 341 ticks while the host said "driving (cmd)". The real command then arrives at a seq already
    taken, with other content: two senders on one epoch. The vehicle stops until that has not happened for the
    silence timeout; a replayed copy of a command taken is not a conflict."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    t = 100.0
    for k in range(1, 11):  # the station at 10 Hz
        assert g.offer(M.Command(stamp=t - 50, seq=k, v=0.2, omega=0.0, method="scm", epoch=STATION), t)
        t += 0.1
    assert g.decide(t - 0.05).reason == "cmd"
    applied_forged = 0
    for k in range(11, 41):  # 3 s: each real command, then the forger's copy at seq + 1 one ms after it
        g.offer(M.Command(stamp=t - 50, seq=k, v=0.2, omega=0.0, method="scm", epoch=STATION), t)
        g.offer(M.Command(stamp=t - 50 + 0.001, seq=k + 1, v=0.5, omega=1.0, method="scm", epoch=STATION), t + 0.001)
        for dt in (0.002, 0.05, 0.098):  # the host's ticks until the next real command
            d = g.decide(t + dt)
            applied_forged += d.v == 0.5
        t += 0.1
    assert applied_forged <= 3, applied_forged  # at most until the next real command (one tick of 10 Hz)
    assert g.decide(t - 0.05) == Decision(0.0, 0.0, "conflict", 40 + 1)
    assert g.counters["seq_conflicts"] >= 29 and "two senders on one command epoch" in g.conflict(t)
    for k in range(42, 52):  # the forger stops; the station goes on: driving again once it has been quiet 0.3 s
        g.offer(M.Command(stamp=t - 50, seq=k, v=0.2, omega=0.0, method="scm", epoch=STATION), t)
        t += 0.1
    assert g.decide(t - 0.05) == Decision(0.2, 0.0, "cmd", 51)
    # a replayed copy of a command taken is a duplicate, not a second sender
    before = g.counters["seq_conflicts"]
    assert not g.offer(M.Command(stamp=t - 0.1 - 50, seq=51, v=0.2, omega=0.0, method="scm", epoch=STATION), t)
    assert g.counters["seq_conflicts"] == before and g.decide(t + 0.01).reason == "cmd"


def test_seq_gate_allows_gaps_from_lost_messages() -> None:
    s = SeqGate(silence_s=0.5)
    assert s.accept(7, 1, 0.0) is None
    assert s.accept(7, 40, 0.1) is None  # 38 lost: within slack + rate
    assert s.accept(7, 40, 0.2) == "out_of_order"


def test_a_stop_is_a_stop_whatever_the_limits() -> None:
    """Findings: Command(method="stop", v=0.4) was applied as 0.4 m/s; with hard limits v = [0.2, 0.5] a zero
    command was clamped up to 0.2 m/s."""
    g = CommandGate(Bounds((0.2, 0.5), (-1.0, 1.0)), cmd_timeout=0.3)
    g.offer(_cmd(1, 0.4, 0.3, method="stop"), 0.0)
    assert g.decide(0.01) == Decision(0.0, 0.0, "stop", 1)
    g.offer(_cmd(2, 0.0, 0.0), 0.02)
    assert g.decide(0.03) == Decision(0.0, 0.0, "stop", 2)
    g.offer(_cmd(3, 0.6, 0.0), 0.04)  # not a stop: clamped into the limits, in its own direction
    assert g.decide(0.05) == Decision(0.5, 0.0, "clamped", 3)


def test_a_command_the_vehicle_cannot_do_in_its_direction_is_a_stop_never_mirrored() -> None:
    """Finding: with hard limits v = [0.05, ...], v = -99 reached the vehicle as +0.05 (and (0, 0.3) as
    (0.05, 0.3)): clamping turned a request into motion the other way."""
    g = CommandGate(Bounds((0.05, 0.5), (0.1, 1.0)), cmd_timeout=0.3)
    cases = [((-99.0, 0.3), None), ((0.0, 0.3), None), ((0.03, 0.3), None), ((0.2, -0.5), None),
             ((0.9, 0.3), (0.5, 0.3)), ((0.2, 5.0), (0.2, 1.0)), ((0.2, 0.5), (0.2, 0.5))]
    for k, ((v, w), want) in enumerate(cases, start=1):
        g.offer(_cmd(k, v, w), 0.01 * k)
        d = g.decide(0.01 * k + 0.001)
        if want is None:
            assert d == Decision(0.0, 0.0, "refused", k), (v, w, d)
        else:
            assert (d.v, d.omega) == want and d.driving, (v, w, d)
    assert g.counters["refused_range"] == 4


def test_a_forged_jump_inside_the_real_epoch_locks_the_station_out_for_a_few_commands_at_most() -> None:
    """Finding: a forged Command with the station's epoch and seq + 135, sent 90 ms after a real one, was applied
    and then locked the real station (10 Hz) out for 13.5 s."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    t = 100.0
    for k in range(1, 21):  # the real station: 10 Hz, stamps on its own clock (1000 s off ours), 2 ms latency
        assert g.offer(M.Command(stamp=t - 1000.0 - 0.002, seq=k, v=0.1, omega=0.0, method="scm", epoch=STATION), t)
        t += 0.1
    last = 20
    forged = M.Command(stamp=t - 1000.0 - 0.01, seq=last + 135, v=0.5, omega=1.0, method="scm", epoch=STATION)
    assert not g.offer(forged, t - 0.01)  # 135 seqs in 90 ms: no station counts that fast
    assert g.counters["seq_jump"] == 1
    ahead = M.Command(stamp=t - 1000.0 + 5.0, seq=last + 2, v=0.5, omega=1.0, method="scm", epoch=STATION)
    assert not g.offer(ahead, t - 0.005)  # stamped 5 s after it arrived: not the station's clock
    assert g.counters["stamp_jump"] == 1
    # the worst a forger inside the epoch can do: the largest jump the rate bound lets through
    sneaky = M.Command(stamp=t - 1000.0 - 0.004, seq=last + 5, v=0.5, omega=1.0, method="scm", epoch=STATION)
    assert g.offer(sneaky, t - 0.004)
    refused = 0
    for k in range(last + 1, last + 12):  # the real station goes on at 10 Hz
        ok = g.offer(M.Command(stamp=t - 1000.0 - 0.002, seq=k, v=0.1, omega=0.0, method="scm", epoch=STATION), t)
        refused += not ok
        t += 0.1
    assert refused <= 2 and g.counters["resyncs"] == 1, (refused, g.counters)
    assert g.latest is not None and g.latest.v == 0.1 and g.latest.seq == last + 11


def test_only_a_configured_source_releases_a_latched_estop() -> None:
    """Finding: Estop(engaged=False, stamp=0, seq=0) from an unrelated session released a latched estop."""
    g = CommandGate(LIMITS, cmd_timeout=0.3, release_sources=("operator",))
    g.offer(_cmd(1, 0.2, 0.0), 0.0)
    assert g.estop(M.Estop(stamp=0.0, source="anyone", reason="button"))  # anyone may stop the robot
    g.offer(_cmd(2, 0.2, 0.0), 0.05)
    assert g.decide(0.06).reason == "estop"
    assert not g.estop(M.Estop(stamp=0.0, engaged=False))
    assert not g.estop(M.Estop(stamp=0.0, engaged=False, source="fuzzer"))
    assert g.decide(0.07).reason == "estop" and g.counters["estop_release_refused"] == 2
    assert g.estop(M.Estop(stamp=0.0, engaged=False, source="operator", reason="area clear"))
    g.offer(_cmd(3, 0.2, 0.0), 0.08)
    assert g.decide(0.09).reason == "cmd"


@settings(max_examples=200, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(allow_nan=True, allow_infinity=True),
       st.sampled_from(["scm", "stop", "direct"]))
def test_whatever_arrives_the_gate_only_ever_emits_finite_bounded_commands(v: float, w: float, method: str) -> None:
    raw = msgspec.msgpack.encode({"stamp": 1.0, "seq": 1, "v": v, "omega": w, "method": method})
    g = CommandGate(LIMITS)
    try:
        g.offer(M.decode(raw, M.Command), 0.0)
    except M.MessageError:
        pass
    d = g.decide(0.01)
    assert math.isfinite(d.v) and math.isfinite(d.omega) and LIMITS.contains([d.v, d.omega])
    if method == "stop":
        assert (d.v, d.omega) == (0.0, 0.0)


def test_a_forged_new_epoch_during_a_dropout_does_not_lock_the_real_sender_out() -> None:
    s = SeqGate(silence_s=0.3)
    assert s.accept(1, 10, 0.0) is None
    assert s.accept(666, 0, 0.5) is None  # forged, while the real sender was silent: followed for now
    assert s.accept(1, 11, 0.6) == "foreign_epoch"  # the forger's stream is alive
    assert s.accept(1, 10, 1.0) == "old_epoch"  # a replay of the real sender's past is still refused
    assert s.accept(1, 12, 1.0) is None  # the forger went silent: the real sender is back


def test_a_station_whose_first_commands_came_late_is_not_taken_for_a_forger() -> None:
    """Found in a loaded fleet demo: a station's first commands reached the driver host 0.3 s late; every later one
    then looked stamped ahead of its own receipt ("forged ... stamp_jump"), was refused for good, and the robot
    never moved. The first commands of an epoch only teach the gate the sender's clock; and a sender whose clock
    was learned during a longer stall is followed again after a few in-order commands."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    t = 100.0
    for seq in range(1, 4):  # a slow start: each arrives 0.3 s after its stamp
        t += 0.1
        assert g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=STATION), t + 0.3)
    for seq in range(4, 10):  # the machine recovers: 2 ms of latency, still within the clock's learning
        t += 0.1
        assert g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=STATION), t + 0.002)
    assert g.counters["stamp_jump"] == 0 and g.conflict(t + 0.01) is None
    # one forged command stamped ahead is refused once the clock is learned
    for seq in range(10, 13):
        t += 0.1
        assert g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=STATION), t + 0.002)
    assert not g.offer(M.Command(stamp=t + 0.5, seq=13, v=0.5, omega=1.0, method="scm", epoch=STATION), t + 0.01)
    assert g.counters["stamp_jump"] == 1


def _learned_late(g: CommandGate, t: float, n: int = 12, late: float = 0.3) -> tuple[float, int]:
    """``n`` commands that each arrive ``late`` after their stamp (a stall that outlasts the clock's learning)."""
    for seq in range(1, n + 1):
        t += 0.1
        assert g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=STATION), t + late)
    return t, n


def test_a_sender_faster_than_the_clock_learned_in_a_long_stall_is_followed_again() -> None:
    g = CommandGate(LIMITS, cmd_timeout=0.5)
    t, last = _learned_late(g, 100.0)
    verdicts = []
    for seq in range(last + 1, last + 7):  # the machine recovers: 2 ms of latency
        t += 0.1
        verdicts.append(g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=STATION),
                                t + 0.002))
    assert verdicts[:2] == [False, False] and all(verdicts[2:]), verdicts
    assert g.counters["resyncs"] == 1 and g.conflict(t + 0.01) is None
    assert not g.offer(M.Command(stamp=t + 0.5, seq=seq + 1, v=0.5, omega=1.0, method="scm", epoch=STATION), t + 0.01)
    assert g.counters["stamp_jump"] == 3


def test_a_station_read_in_batches_after_a_long_stall_is_followed_again() -> None:
    """Found beside two busy loops: commands read in batches (one per stall of a starved driver host) have
    latencies that differ by the send period, so a resync that asked the ahead commands to agree on one latency
    never came: the station was refused as a forger ("stamp_jump") for as long as the batches went on. In-order
    commands are the sender, batched or not."""
    g = CommandGate(LIMITS, cmd_timeout=0.5)
    t, seq = _learned_late(g, 100.0)
    verdicts = []
    for _ in range(4):  # every 0.3 s the host reads the three commands sent (10 Hz) since its last read
        read_at = t + 0.3
        for _k in range(3):
            seq, t = seq + 1, t + 0.1
            verdicts.append(g.offer(M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm", epoch=STATION),
                                    read_at + 0.001))
    assert verdicts[:2] == [False, False] and all(verdicts[2:]), verdicts
    assert g.counters["resyncs"] == 1 and g.conflict(t + 1.0) is None
    # the clock was learned from the whole run: the batch's freshest command sets it, so no later one looks ahead
    assert g.counters["stamp_jump"] == 2
    assert not g.offer(M.Command(stamp=t + 0.5, seq=seq + 1, v=0.5, omega=1.0, method="scm", epoch=STATION), t + 0.4)


def test_a_restarted_station_whose_first_tick_was_slow_is_never_called_a_forger() -> None:
    """Found beside two busy loops: a restarted station's first command (stamped at the start of its first,
    slowest tick) taught the gate a 0.3 s latency; the next ones looked ahead, were refused as forged, and the
    driver host's status said so just when the operator resumed the mission: refused. A new epoch's first
    commands only teach the gate its clock."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    t, seq = _learned_late(g, 100.0, late=0.002)
    t += 1.0  # the station is killed: silence, then its new run
    new = STATION + 1
    assert g.offer(M.Command(stamp=t, seq=0, v=0.0, omega=0.0, method="stop", epoch=new), t + 0.3)
    for k in range(1, 20):
        t += 0.1
        assert g.offer(M.Command(stamp=t, seq=k, v=0.0, omega=0.0, method="stop", epoch=new), t + 0.002)
    assert g.counters["stamp_jump"] == 0 and g.conflict(t + 0.01) is None


def test_a_stall_of_a_few_seconds_does_not_make_the_station_look_like_a_forger_afterwards() -> None:
    """Found beside two busy loops (a fleet demo robot paused mid-mission): a driver host starved for a few seconds
    got every command late, the learned least latency rose with them, and once the host was fast again the station's
    commands looked stamped ahead: refused as forged, and the station paused its mission. The least latency is
    kept over a minute."""
    g = CommandGate(LIMITS, cmd_timeout=0.5)
    t, last = _learned_late(g, 100.0, n=20, late=0.002)
    for k in range(1, 91):  # 8 s of a starved host (each command read 0.25 s late), then fast again
        t += 0.1
        late = 0.25 if k <= 80 else 0.002
        assert g.offer(M.Command(stamp=t, seq=last + k, v=0.2, omega=0.0, method="scm", epoch=STATION), t + late)
    assert g.counters["stamp_jump"] == 0 and g.conflict(t) is None


def test_a_forged_jump_while_the_clock_is_still_learned_locks_the_station_out_for_a_few_commands_at_most() -> None:
    """The first commands of an epoch only teach the gate the clock; a forged jump among them must still not lock
    the real station out (its in-order, fresh commands below the jump are followed again)."""
    g = CommandGate(LIMITS, cmd_timeout=0.3)
    t = 100.0
    for k in range(1, 4):
        t += 0.1
        assert g.offer(M.Command(stamp=t, seq=k, v=0.1, omega=0.0, method="scm", epoch=STATION), t + 0.002)
    assert g.offer(M.Command(stamp=t + 0.01, seq=8, v=0.5, omega=1.0, method="scm", epoch=STATION), t + 0.012)
    verdicts = []
    for k in range(4, 10):
        t += 0.1
        verdicts.append(g.offer(M.Command(stamp=t, seq=k, v=0.1, omega=0.0, method="scm", epoch=STATION), t + 0.002))
    assert not all(verdicts[:2]) and all(verdicts[3:]), verdicts
