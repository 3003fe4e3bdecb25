"""``scmbridge bench attack --short``: every attack a hostile probe found, run against the real components; nothing
unsafe reaches a vehicle and nothing implausible is learned (each attack is also tested where it is fixed)."""

from __future__ import annotations

import pytest

from bench.attack import ATTACKS, run_all
from bench.attack_files import FILE_ATTACKS
from bench.attack_trust import TRUST_ATTACKS


@pytest.mark.slow
def test_no_attack_gets_through() -> None:
    res = run_all(short=True)
    failed = [a for a in res["attacks"] if not a["ok"]]
    assert not failed, failed
    assert [a["attack"] for a in res["attacks"]] == [*ATTACKS, *TRUST_ATTACKS, *FILE_ATTACKS] and res["all_ok"]
