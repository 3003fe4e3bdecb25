"""``scmbridge bench attack --short``: every attack a hostile probe found, run against the real components; nothing
unsafe reaches a vehicle and nothing implausible is learned (each attack is also tested where it is fixed). One test
per attack, each through ``run_all`` as the command runs it, so the suite's workers share them out and a failure
names its attack."""

from __future__ import annotations

import pytest

from bench.attack import ATTACKS, run_all
from bench.attack_files import FILE_ATTACKS
from bench.attack_trust import TRUST_ATTACKS

EVERY = [*ATTACKS, *TRUST_ATTACKS, *FILE_ATTACKS]


def test_every_attack_has_a_name_of_its_own() -> None:
    """``run_all`` runs the three tables merged into one (by name): a name two tables share would lose an attack."""
    assert len(set(EVERY)) == len(EVERY) == len(ATTACKS) + len(TRUST_ATTACKS) + len(FILE_ATTACKS)


@pytest.mark.parametrize("name", EVERY)
def test_no_attack_gets_through(name: str) -> None:
    res = run_all(short=True, names=[name])
    failed = [a for a in res["attacks"] if not a["ok"]]
    assert not failed, str(failed)  # (a str: pytest shows it whole, not a repr cut at its first levels)
    assert [a["attack"] for a in res["attacks"]] == [name] and res["all_ok"]
