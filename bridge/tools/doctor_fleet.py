"""``scmbridge doctor``'s look at the robots themselves: each driver host is asked over Zenoh for its estop latch
and its state, and the local state directory is read only for a host on this machine (docs/OPERATING.md, "Before
a lab drives").

An operator's console is not a robot: the estop latch that matters is on the robot's own disk, in its driver host's
state directory, and only that host can say what it holds. So the robots are asked, as ``estop --all`` and ``status
--all`` ask them: every driver host answers a query on ``scm/<robot>/estop`` with its latch (who latched it, or
released) and one on ``scm/<robot>/status/driver`` with its last status, whose ``host`` names its machine and boot.
Each line says which robot answered from where (``this machine`` or its host's name), and :func:`local_robots`
gives the robots whose driver host runs here, the only ones whose latch files doctor may read in this machine's
state directory.
"""

from __future__ import annotations

import time

import zenoh

from bridge.core import wire as M
from bridge.core.clock import machine
from bridge.core.errors import UsageError
from bridge.nodes.zsession import open_session
from bridge.tools.estop import ALL, latch_states


def ask_robots(conf: zenoh.Config, listen_s: float) -> tuple[dict[str, list[M.EstopState]], dict[str, M.Status]]:
    """Every driver host's latch (``scm/*/estop``, per robot) and last status (``scm/*/status/driver``), within
    ``listen_s``; raises :class:`UsageError` when the router cannot be reached (its own check says so)."""
    latches: dict[str, list[M.EstopState]] = {}
    statuses: dict[str, M.Status] = {}
    with open_session(conf) as session:
        t_end = time.monotonic() + listen_s

        def take(sample: zenoh.Sample) -> None:
            robot = str(sample.key_expr).split("/")[1]
            try:
                statuses[robot] = M.decode(sample.payload.to_bytes(), M.Status)
            except M.MessageError:
                pass

        sub = session.declare_subscriber(f"{M.PREFIX}/*/status/driver", take)  # a host too old to answer queries
        try:
            for name, st in latch_states(session, ALL, max(0.1, min(1.0, listen_s))).items():  # robot/node
                latches.setdefault(name.split("/")[0], []).append(st)
            for reply in session.get(f"{M.PREFIX}/*/status/driver", timeout=max(0.1, t_end - time.monotonic()),
                                     consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is not None:
                    take(reply.ok)
            while set(latches) - set(statuses) and time.monotonic() < t_end:
                time.sleep(0.05)
        finally:
            sub.undeclare()
    return latches, statuses


def where(status: M.Status | None) -> str:
    """Where a driver host runs, in words: ``this machine``, its host's name, or unknown (an older host)."""
    if status is None or status.host is None:
        return "a host that did not say where"
    return "this machine" if status.host == machine() else f"host {status.host.split('/', 1)[0]}"


def local_robots(statuses: dict[str, M.Status]) -> list[str]:
    """The robots whose driver host runs on this machine (same machine and boot: ``Status.host``)."""
    return sorted(r for r, st in statuses.items() if st.host == machine())


def robot_checks(latches: dict[str, list[M.EstopState]], statuses: dict[str, M.Status]) -> list[tuple[str, str]]:
    """One ``(level, text)`` per robot heard: its latch as its driver host holds it and its state, and where the host
    runs."""
    out = []
    for robot in sorted(set(latches) | set(statuses)):
        st = statuses.get(robot)
        said = f"{robot} (driver host on {where(st)})"
        state = f"; state {st.state or '?'}: {st.text}" if st is not None else "; no status heard"
        held = latches.get(robot, [])
        if not held:
            out.append(("warn", f"{said}: did not answer the estop query (its latch is unknown){state}"))
        elif any(e.latched for e in held):
            by = ", ".join(sorted({e.source or "unknown" for e in held if e.latched}))
            out.append(("warn", f"{said}: estop latched by {by} (look at the robot, then scmbridge estop --robot "
                                f"{robot} --release){state}"))
        else:
            out.append(("ok", f"{said}: estop released, as its driver host holds it{state}"))
    return out


def fleet_report(conf: zenoh.Config, listen_s: float) -> tuple[list[tuple[str, str]], list[str] | None]:
    """The robots' lines and the robots whose driver host runs here; (a line saying why, None) when the router
    cannot be reached."""
    try:
        latches, statuses = ask_robots(conf, listen_s)
    except UsageError as exc:
        return [("warn", f"the robots were not asked: {exc}")], None
    lines = robot_checks(latches, statuses)
    if not lines:
        lines = [("warn", f"no driver host answered within {listen_s:g} s: none is running, or this identity may "
                          "not ask them (the operator's or the observer's certificate may)")]
    return lines, local_robots(statuses)


__all__ = ["ask_robots", "fleet_report", "local_robots", "robot_checks", "where"]
