"""The station's check of the method's assumption (bridge.nodes.station_assumption) in the real station core: a
car measured to turn less than the mission's path bends is paused at its start, inside the corridor, with the typed
reason ``outside_assumption`` and the numbers on its status; a feasible car, a car with nothing measured and a
vehicle that turns in place drive on; a person's resume drives on."""

from __future__ import annotations

import msgspec

from bridge.core.config import StationConfig
from bridge.nodes.station_core import TickInputs
from tests.unit.bridge.nodes.test_station_guards import Run, _driver, _line


def _cfg(turn: str = "needs-speed", reach: list[float] | None = None) -> StationConfig:
    return msgspec.convert({"transfer": {"turn": turn, "turn_reach": reach or []}}, StationConfig)


def test_a_car_that_cannot_turn_the_paths_bends_is_paused_at_its_start_and_says_why(tmp_path) -> None:
    run = Run(tmp_path, cfg=_cfg(reach=[0.37, 0.40, 0.33]))
    run.poses([(0.0, 0.0)])
    assert run.ask("start").accepted
    run.poses(_line((0.0, 0.0), (0.05, 0.05)))
    st = run.status()
    assert run.core.control.phase == "paused" and st.reason == "outside_assumption" and not st.ok
    assert "outside the method's assumption" in st.text and "0.73 rad/m" in st.text, st.text
    assert "0.37 rad/m at 0.33 m/s" in st.text and "right" in st.text, st.text
    assert st.off_path_m is not None and st.off_path_m < 0.5  # stopped inside the corridor
    out = run.core.tick(TickInputs(driver=(_driver(), run.t)), run.t)  # and the robot is stopped
    assert out.command is not None and out.command.method == "stop" and (out.command.v, out.command.omega) == (0, 0)
    # a person resumes: the operator wins, the station drives on (the corridor still guards)
    assert run.ask("resume").accepted
    run.poses(_line((0.05, 0.05), (0.1, 0.1)))
    assert run.core.control.phase == "running"


def test_a_feasible_car_a_car_not_measured_and_a_skid_steer_drive_on(tmp_path) -> None:
    for i, cfg in enumerate((_cfg(reach=[0.9, 0.9, 0.3]), _cfg(), _cfg("in-place", [0.2, 0.2, 0.3]))):
        run = Run(tmp_path / str(i), cfg=cfg)
        run.poses([(0.0, 0.0)])
        assert run.ask("start").accepted
        run.poses(_line((0.0, 0.0), (0.1, 0.1)))
        assert run.core.control.phase == "running", (i, run.status().text)
