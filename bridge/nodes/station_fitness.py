"""Whether the station may drive its robot now, judged from the latest driver host status and pose (pure: the times
are arguments; docs/ARCHITECTURE.md, "A person is in charge").

The robot is fit when the driver host's status is fresh (one each second; :data:`DRIVER_STATUS_MAX_AGE`) and
``ok`` (link up, engaged, no fault, no estop), and the latest pose arrived less than ``max_pose_age`` ago.
:func:`why_not_drive` gives the one reason it is not (None: it is); :func:`assess_fitness` adds what mission control
(:class:`bridge.nodes.mission_control.Fitness`) decides a pause on: whether that reason is a latched estop (a resume
is refused until it is released), and whether the driver host itself refuses (the mission pauses at once) rather
than a pose or a status being late (it pauses only once that has lasted, a loaded moment is not a lost link).
Decided on typed fields only (the driver host's ``ok`` and ``reason``, the stamps): its ``text`` is only quoted.
"""

from __future__ import annotations

from bridge.core import wire as M
from bridge.nodes.mission_control import Fitness
from bridge.nodes.sources import Why

#: a driver host publishes status each second: after this long without one, the robot is not known to be fit
DRIVER_STATUS_MAX_AGE = 3.0


def driver_estop(driver: M.Status) -> bool:
    """Whether a driver host's status says an estop is latched there: its typed reason (``estop``, also in a dry
    run; ``latch_unsaved``: latched and not on its disk), never its words; a host older than that field says it by
    its state alone."""
    if driver.reason is not None:
        return driver.reason in ("estop", "latch_unsaved")
    return driver.state == "estop"


def why_not_drive(now: float, state: M.LearnerState | None, state_at: float, driver: M.Status | None,
                  driver_at: float, max_pose_age: float) -> Why | None:
    """None if the station may drive the robot now, else why not (typed, and in words for status and the log).
    ``state_at`` / ``driver_at``: when the latest pose and driver host status were received (this host's clock)."""
    if driver is None or now - driver_at > DRIVER_STATUS_MAX_AGE:
        return Why("robot not ready: no driver host status", "robot_not_ready")
    if not driver.ok:
        return Why(f"robot not ready: {driver.text}", "robot_not_ready")
    if state is None:
        return Why("no pose yet", "no_telemetry")
    if now - state_at > max_pose_age:
        return Why(f"no pose for {now - state_at:.1f} s", "no_telemetry")
    return None


def assess_fitness(now: float, state: M.LearnerState | None, state_at: float, driver: M.Status | None,
                   driver_at: float, max_pose_age: float) -> tuple[Why | None, Fitness]:
    """Why the robot may not be driven now (None: it may), and the :class:`Fitness` mission control decides on.

    ``immediate`` is true only when a fresh driver host status says not ok (the host refuses: an estop, the operator,
    a fault): that pauses a running mission at once. A status or a pose that is late is not the host's refusal,
    and pauses only once it has lasted :data:`bridge.nodes.mission_control.PAUSE_AFTER_S`."""
    why_not = why_not_drive(now, state, state_at, driver, driver_at, max_pose_age)
    estop = driver is not None and driver_estop(driver)
    host_refuses = driver is not None and now - driver_at <= DRIVER_STATUS_MAX_AGE and not driver.ok
    return why_not, Fitness(why_not.text if why_not is not None else "", estop, immediate=host_refuses)


__all__ = ["DRIVER_STATUS_MAX_AGE", "assess_fitness", "driver_estop", "why_not_drive"]
