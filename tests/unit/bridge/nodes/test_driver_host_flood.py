"""A flood of refused acts is counted, and logged in a bounded number of lines: the driver host's log stays readable
when one source floods it (docs/SECURITY.md, ``acts_flood_one_identity``), the counter says how many."""

from __future__ import annotations

import logging

from bridge.core import wire as M
from bridge.core.acts import Address, stamped
from bridge.nodes.driver_config import DriverConfig
from bridge.nodes.driver_host import DriverHost
from drivers.base import LinkHealth


class _Link:
    name = "fixed"

    def health(self, now: float) -> LinkHealth:
        return LinkHealth(connected=True, ok=True, text="ok")


class _Query:
    """What the host reads of a Zenoh query and what it answers (the answer kept)."""

    def __init__(self, payload: bytes) -> None:
        self.payload = _Bytes(payload)
        self.replies: list[bytes] = []

    def reply(self, key: str, payload: bytes) -> None:
        self.replies.append(payload)


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


def test_four_thousand_refused_acts_are_all_counted_and_logged_in_about_a_dozen_lines(caplog) -> None:
    host = DriverHost(DriverConfig(), "mavlink", _Link(), "r1", 50.0)
    to = Address(host.acts.epoch, 0.0)  # addressed to this start, stamped long ago: each one "stale"
    caplog.set_level(logging.DEBUG, logger="scmbridge")
    answers = []
    for _ in range(4096):
        q = _Query(M.encode(stamped(M.EngageRequest(stamp=1.0, source="mallory"), to)))
        host.on_engage_query(q)
        answers += [M.decode(r, M.EngageState) for r in q.replies]
    assert len(answers) == 4096 and not any(a.accepted for a in answers)
    kinds = {k: v for k, v in host.inputs.snapshot().items() if k.startswith("engage_refused_")}
    assert sum(kinds.values()) == 4096, kinds
    lines = [r for r in caplog.records if "engage by 'mallory'" in r.getMessage()]
    assert 1 <= len(lines) <= 13, len(lines)  # 1, 2, 4, ... 4096 of each kind
    assert "4096 refused so" in lines[-1].getMessage() or len(kinds) > 1
