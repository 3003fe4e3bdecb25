"""The fence upload's pure parts (drivers/mavlink/fence.py): lab-frame vertices placed from the EKF origin as
ArduPilot's Location::offset does, a polygon checked before anything is sent, the vehicle's answers read by type and
mission_type; and the driver host's ``--fence`` refused where no autopilot holds one. (The upload itself runs against
ArduPilot SITL: tests/integration/test_fence_sitl.py.)"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from bridge.core.config import ConfigError, load_fence
from drivers.base import DriverError
from drivers.mavlink.fence import LOCATION_SCALING_FACTOR, MISSION_TYPE_FENCE, FenceUpload, check_polygon, to_global

CMAC = (-353632640, 1491652352)  # SITL's default home, 1e-7 degree


def test_a_vertex_is_placed_east_and_north_of_the_origin_as_ardupilot_places_it() -> None:
    lat, lon = to_global(CMAC, 0.0, 10.0)
    assert lon == CMAC[1] and (lat - CMAC[0]) * LOCATION_SCALING_FACTOR == pytest.approx(10.0, abs=0.006)
    lat, lon = to_global(CMAC, 10.0, 0.0)
    scale = math.cos(math.radians(CMAC[0] * 1e-7))
    assert lat == CMAC[0] and (lon - CMAC[1]) * LOCATION_SCALING_FACTOR * scale == pytest.approx(10.0, abs=0.006)


def test_a_fence_needs_three_finite_vertices() -> None:
    assert check_polygon([[0, 0], [1, 0], [1, 1]]) == [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)]
    for bad in ([[0, 0], [1, 0]], [[0, 0], [1, 0], [math.nan, 1]]):
        with pytest.raises(DriverError):
            check_polygon(bad)


def _msg(kind: str, **fields):
    return SimpleNamespace(get_type=lambda: kind, **fields)


def test_only_the_fences_mission_messages_count() -> None:
    up = FenceUpload((1, 1))
    up.on_message(_msg("MISSION_REQUEST_INT", seq=0, mission_type=0))  # a mission upload's, not the fence's
    up.on_message(_msg("MISSION_ACK", type=0, mission_type=0))
    assert up.requested == [] and up.ack is None
    up.on_message(_msg("MISSION_REQUEST_INT", seq=0, mission_type=MISSION_TYPE_FENCE))
    up.on_message(_msg("MISSION_REQUEST", seq=1, mission_type=MISSION_TYPE_FENCE))
    up.on_message(_msg("MISSION_ACK", type=0, mission_type=MISSION_TYPE_FENCE))
    up.on_message(_msg("GPS_GLOBAL_ORIGIN", latitude=CMAC[0], longitude=CMAC[1], altitude=0))
    up.on_message(_msg("PARAM_VALUE", param_id="FENCE_TYPE\x00", param_value=4.0))
    assert up.requested == [0, 1] and up.ack == 0 and up.origin == CMAC and up.params == {"FENCE_TYPE": 4.0}


def test_the_fence_comes_from_a_mission_file_or_a_station_configuration(tmp_path) -> None:
    station = tmp_path / "station.toml"
    station.write_text("[station]\nfence = [[0, 0], [5, 0], [5, 5]]\n")
    assert load_fence(station) == [(0.0, 0.0), (5.0, 0.0), (5.0, 5.0)]
    mission = tmp_path / "mission.toml"
    mission.write_text('path = [[0, 0], [1, 0]]\nfence = [[-1, -1], [2, -1], [2, 2], [-1, 2]]\n')
    assert len(load_fence(mission)) == 4
    none = tmp_path / "none.toml"
    none.write_text("[station]\nrate_hz = 10.0\n")
    with pytest.raises(ConfigError, match="no fence"):
        load_fence(none)
    short = tmp_path / "short.toml"
    short.write_text("[station]\nfence = [[0, 0], [5, 0]]\n")
    with pytest.raises(ConfigError):
        load_fence(short)


def test_the_driver_host_refuses_a_fence_on_a_link_whose_vehicle_cannot_hold_one(tmp_path) -> None:
    import subprocess
    import sys

    station = tmp_path / "station.toml"
    station.write_text("[station]\nfence = [[0, 0], [5, 0], [5, 5]]\n")
    done = subprocess.run([sys.executable, "-m", "bridge", "driver", "--link", "can", "--emulate", "--fence",
                           str(station), "--duration", "1"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--fence uploads ArduPilot's own fence" in done.stderr, done.stderr
