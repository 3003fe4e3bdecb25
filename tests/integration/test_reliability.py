"""The reliability suite at a small size: ``scmbridge bench fuzz`` and ``scmbridge bench soak`` (bench/).

Each fuzzed input (2000 payloads) must be counted exactly by its receiver, crash nothing, never give a vehicle a
non-finite or out-of-limits command, and leave the link able to drive. The long forms (100k payloads per input, RSS
rounds, a soak of minutes) are benchmarks: docs/RELIABILITY.md. Processes are always stopped, sessions closed,
traffic stays on 127.0.0.1 ports bound here and python-can ``virtual`` channels.
"""

from __future__ import annotations

import json

import pytest

from bench import soak
from bench.fuzz import can_frames, harness, host, mavlink_frames, messages, rss
from bench.fuzz.main import IN_PROCESS
from bridge.core import wire as M

N = 2000


def check(res: dict, name: str) -> None:
    """Exact counts, the vehicle side, driving afterwards, no crash. (The fuzz found two emulator crashes, a remote
    frame killing the old emulated ODrive controllers and a NaN/inf command parameter killing the emulated rover;
    a NaN set-point reaching the rover's vehicle; and an infinite ATTITUDE yaw raising out of the MAVLink driver's
    ``poll()``. All are fixed, so any crash fails.)"""
    assert res["sent"] == N, res
    assert res["exact"], {k: v for k, v in res.items() if "kinds" not in k}
    assert res.get("contract_violations", 0) == 0, res
    if "vehicle" in res:
        assert res["vehicle"]["ok"], res["vehicle"]
    if "drives_after" in res:
        assert res["drives_after"]["ok"], res["drives_after"]
    assert not res["crashes"], res["crash_events"]


@pytest.fixture(scope="module")
def zenoh_results(tmp_path_factory) -> dict:
    """Both Zenoh inputs into one driver host process (saves a start-up)."""
    return host.fuzz_zenoh(N, 7, tmp_path_factory.mktemp("fuzz"))


@pytest.mark.parametrize("name", ["zenoh_cmd", "zenoh_estop"])
def test_zenoh_inputs_into_a_driver_host_are_counted_exactly(zenoh_results, name) -> None:
    res = zenoh_results[name]
    check(res, name)
    echoes = res["vehicle"]["applied_echoes"]
    assert echoes["n"] > 50 and echoes.get("bad", 0) == 0  # every applied echo decoded: finite, in range
    assert res["rss_mb"]["before"] and res["rss_mb"]["after"]


def test_the_estop_latch_counts_follow_the_documented_rule(zenoh_results) -> None:
    latch = zenoh_results["zenoh_estop"]["latch_counters"]
    assert latch["host"] == latch["rule"] and latch["rule"]["estops"] > 10 and latch["rule"]["estop_releases"] > 10


@pytest.mark.parametrize("name", ["udp_driver", "udp_robot", "can_decoder", "can_driver", "can_ecu", "mavlink_driver",
                                  "mavlink_rover"])
def test_in_process_inputs_are_counted_exactly(name, tmp_path) -> None:
    res = IN_PROCESS[name](N, 11, tmp_path)
    assert res["counted"] > N // 10, res  # the mutations really are malformed, mostly
    check(res, name)


def test_oracles_refuse_what_the_contract_refuses() -> None:
    """The mutation kinds that must be malformed are, by the wire contract (and the CAN/MAVLink oracles agree with
    their libraries on plain examples)."""
    import random

    rng = random.Random(3)
    tally = harness.Tally()
    mut = messages.MsgMutator(rng, messages.COMMAND, messages.CommandStream(rng))
    for _ in range(3000):
        kind, data = mut.next()
        tally.add(kind, not messages.wire_ok(data, M.Command))
    assert tally.contract_violations() == 0 and tally.refused["valid"] == 0
    assert all(tally.sent[k] > 20 for k in harness.MUST_REJECT)
    spec = can_frames.CanSpec()
    assert spec.valid(can_frames.can_frame(1, can_frames.SET_INPUT_VEL, bytes(8)))
    assert not spec.valid(can_frames.can_frame(1, can_frames.SET_INPUT_VEL, bytes(7)))
    assert not spec.valid(can_frames.can_frame(1, can_frames.SET_INPUT_VEL, b"\x00\x00\xc0\x7f" + bytes(4)))  # NaN
    m = mavlink_frames.MavMutator(random.Random(1), mavlink_frames.gcs_templates(random.Random(2)))
    parser = mavlink_frames.mav_parser()
    for _ in range(200):  # sealed: nothing is left pending in a parser after any datagram
        mavlink_frames.mav_parse(parser, m.next()[1])
        assert parser.buf_len() == 0


def test_rss_rounds_and_the_probe_host_report(tmp_path) -> None:
    res = rss.rss_rounds(1, 300, 5, tmp_path, probe=True)
    assert len(res["rss_mb"]) == 2 and all(res["exact"]) and not res["crashes"]
    assert len(res["heap"]) == 2 and res["heap"][0]["python_traced_mb"] > 0
    assert "malloc_free_kept_mb" in res["after_malloc_trim"]
    assert {"anon", "file", "shmem"} <= set(res["parts_mb"][-1])


def test_a_memory_report_names_the_sites_that_grew(tmp_path, monkeypatch) -> None:
    import tracemalloc

    from bridge.nodes.node import MemoryReport

    path = tmp_path / "mem.jsonl"
    untraced = MemoryReport(str(path)).build()
    assert untraced["tracing"] is False and "PYTHONTRACEMALLOC" in untraced["note"]
    tracemalloc.start()
    try:
        rep = MemoryReport(str(path))
        rep.write()
        hoard = [bytearray(4096) for _ in range(500)]  # about 2 MB kept, from this line
        rep.write()
    finally:
        tracemalloc.stop()
    first, second = (json.loads(line) for line in path.read_text().splitlines())
    assert first["baseline"] and second["growth"][0]["site"].endswith(f"test_reliability.py:{_line_of('hoard =')}")
    assert second["growth"][0]["kb"] >= 0.9 * len(hoard) * 4 and second["growth"][0]["blocks"] >= len(hoard)


def _line_of(text: str) -> int:
    from pathlib import Path

    return next(i for i, line in enumerate(Path(__file__).read_text().splitlines(), 1) if text in line)


@pytest.mark.slow
# bounded by the soak's own deadlines (its nodes' start-up 180 s, the traced station's last report 120 s), not by
# pytest's default 120 s, most of which it took in a six-worker suite beside other work
@pytest.mark.timeout(360)
def test_a_short_soak_runs_and_reports(tmp_path) -> None:
    """With the station traced (tracemalloc), it answers SIGUSR1 with its memory report."""
    res = soak.soak(0.1, "can", tmp_path, sample_s=1.0, warmup_s=0.0, trace_memory=("station",))  # 6 s: its plumbing
    assert res["nodes_up"], res  # both nodes spoke before the soak asked for reports
    reports = res["memory_reports"]["station"]
    assert len(reports) == 2 and reports[0]["baseline"] and "growth" in reports[1], reports
    assert "driver" not in res["memory_reports"]
    assert res["processes_alive"], res
    assert len(res["times_s"]) >= 4
    for name in ("driver", "station", "bench"):
        r = res["rss"][name]
        assert r["first_mb"] and r["last_mb"] and r["slope_mb_per_min"] is not None
    for node in ("station", "driver"):
        assert res["missed_deadlines"][node]["total"] is not None
        assert res["last_status"][node]["counters"]
    c = res["last_status"]["station"]["counters"]  # it drove: mapped, direct or exploring commands
    assert c["method_scm"] + c["method_direct"] + c.get("method_perturb", 0) > 0, res["last_status"]["station"]
    assert not any(res["log_errors"].values()), res["log_errors"]
