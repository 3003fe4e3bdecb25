"""``[link.mavlink] source_system`` / ``source_component``: the ids the driver host speaks with beside a ground station
(docs/OPERATING.md, "First day with your rover")."""

from __future__ import annotations

import pytest

from bridge.core.config import Rule
from drivers.mavlink.config import MavlinkLinkConfig


def test_a_ground_stations_ids_by_default_and_a_companions_when_configured() -> None:
    gcs = MavlinkLinkConfig()
    assert (gcs.source_system, gcs.source_component, gcs.companion) == (255, 190, False)
    comp = MavlinkLinkConfig(source_system=1, source_component=191)
    assert comp.companion


def test_the_autopilots_own_ids_are_refused() -> None:
    with pytest.raises(Rule, match="autopilot's own ids"):
        MavlinkLinkConfig(source_system=1, source_component=1)
    MavlinkLinkConfig(source_system=2, source_component=1, target_system=2, target_component=191)  # not the same
