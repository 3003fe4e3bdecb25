"""``scmbridge bench bridge --beside-station N`` end to end: a real router, a real driver host on the emulated CAN link,
and a real ``station --robots`` process ticking the fleet bench's simulated robot on the same router for the whole
run; the link's figures and the station's come back. Bounded by the bench's own durations and the timeout here;
every process is the bench's child and goes away with it."""

from __future__ import annotations

import json

import pytest

from bench.bridge import run_link


@pytest.mark.timeout(180)
def test_the_bridge_bench_runs_beside_a_ticking_station(tmp_path) -> None:
    # commands at 50 Hz for at least 2 s and until 100 latencies were measured and the station ticked 20 times (at
    # most a minute more): the host applies the newest command each tick, so a host the machine stalls applies fewer
    # than it was sent, and a fixed window then fell short of the count; counted, it takes longer instead
    res = run_link("can", 2.0, str(tmp_path), beside=1, min_latencies=100, min_beside_ticks=20)
    lat = res["publish_to_driver_send_ms"]
    assert lat is not None and lat["n"] >= 100 and lat["median"] > 0.0, json.dumps(res, indent=1, default=str)
    beside = res["beside_station"]
    # the station drove its robot for the whole run: about 10 ticks a second, reported with its own figures
    assert beside["robots"] == 1 and beside["ticks"] >= 20, beside
    assert beside["missed_deadlines"] >= 0 and beside["tick_p99_ms_worst"] is not None and beside["cpu_cores"] > 0.0
