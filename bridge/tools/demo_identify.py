"""``scmbridge demo --sitl --identify``: the learner's range measured before the mission (:mod:`transfer.identify`),
by the station's own loop (:class:`bridge.nodes.station.Station` running the identification plan as it runs a
calibration plan: the station's commands, the driver host's guards, the person's engage), and the station's
settings that follow from it: the learner's range (the vehicle's parameters only bound it), whether it turns in
place (``[transfer] turn``, and where it starts: ``--start``), how long its pairs wait to settle
(``[station] pair_settle_s``, ``pair_settle_edge_s``). What ``--turn``, ``--start`` and ``--pair-settle`` say
still wins. docs/OPERATING.md says how a lab does the same with its own rover.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from transfer.identify import Identified, IdentifyPlan

#: the teacher's top speed and turn rate (paper Table 2): what the probes aim to find the commands for
TEACHER_TOP = (0.6, 0.7853981633974483)


def identify(station_toml: Path, robot: str, port: int, world: Any, timeout_s: float = 60.0) -> Identified | None:
    """Run the identification through a station in this process, a Zenoh client of the demo's hub on ``port``,
    with the learner bounds of ``station_toml`` as what the vehicle accepts; the measurement, or None if the plan
    did not finish in ``timeout_s``."""
    from bridge.core import wire as M
    from bridge.core.config import load_station
    from bridge.nodes.mission_control import Fitness
    from bridge.nodes.station import Station
    from bridge.nodes.zsession import make_config, open_session, tcp

    cfg = load_station(station_toml)
    plan = IdentifyPlan(cfg.learner_bounds.bounds(), TEACHER_TOP)
    store = station_toml.parent / "identify-pairs.bin"
    store.unlink(missing_ok=True)
    station = Station(cfg, robot, cfg.station.rate_hz, store, world, calibration=plan)  # type: ignore[arg-type]
    station.control.request(M.MissionRequest(stamp=0.0, action="start", source="scmbridge demo --identify"),
                            Fitness("not checked yet"), 0.0)
    with open_session(make_config(mode="client", connect=[tcp(port)])) as session:
        station.serve(session, threading.Event(), timeout_s, exit_at_goal=True, announce=False)
    return plan.result() if plan.finished is not None else None


def settings(ident: Identified, args: Any, v_min: float) -> dict[str, Any]:
    """The station's settings from what was measured (what the demo's flags say wins)."""
    turn = args.turn or ("in-place" if ident.turns_in_place else "needs-speed")
    settle = float(args.pair_settle) if args.pair_settle is not None else round(
        min(1.5, max(0.5, ident.settle_s + 0.2)), 1)
    edge = 0.0
    if args.pair_settle is None and ident.settle_top_s > 1.2:  # a slow body: the edges' probes wait for the top
        edge = round(min(3.0, max(settle, ident.settle_top_s + 0.7)), 1)
    return {"turn": turn, "start": args.start or ("on-path" if turn == "needs-speed" else "mission"),
            "settle": settle, "settle_edge": edge, "v_range": (v_min, max(v_min + 0.05, ident.v_max)),
            "w_range": ident.w_range}
