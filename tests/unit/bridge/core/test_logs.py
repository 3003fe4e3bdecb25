"""A reason said once while it lasts (bridge/core/logs.py): counted while its typed key repeats, and on the next
change how long it held and how often it was decided. The station's use: tests/unit/bridge/nodes/
test_station_core.py."""

from __future__ import annotations

import logging

from bridge.core.logs import ReasonLog


def test_a_reason_is_logged_once_per_key_and_its_run_is_said_when_it_changes(caplog) -> None:
    log = logging.getLogger("scmbridge.test.reasons")
    caplog.set_level(logging.INFO, logger="scmbridge.test.reasons")
    said = ReasonLog(log)
    for k in range(30):  # the words change every tick; the key does not
        said.say(("paused", "no_telemetry"), f"paused: no pose for {0.5 + 0.1 * k:.1f} s", 10.0 + 0.1 * k)
    assert [r.getMessage() for r in caplog.records] == ["paused: no pose for 0.5 s"]
    assert said.say("ok", "driving", 13.0)
    last = caplog.records[-1].getMessage()
    assert last == "driving (after: paused: no pose for 3.4 s; held 3.0 s, decided 30 times)", last
    said.say("ok", "driving", 13.1)
    said.flush(14.0)
    assert caplog.records[-1].getMessage() == "last: driving; held 1.0 s, decided 2 times"
    said.flush(15.0)  # nothing new since
    assert len(caplog.records) == 3
