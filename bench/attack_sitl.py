"""``scmbridge bench attack --sitl``: the MAVLink rows against ArduPilot's own Rover firmware in SITL
(:mod:`sim_learner.sitl`), where the emulated rover (bench/attack.py's rows) stands in for it otherwise.

* ``sitl_host_killed``: a host driving the rover dies without a word; when the rover stops, with Rover's defaults
  and with the GCS failsafe watching the host.
* ``sitl_replay_after_reboot``: a keyed host's signed traffic (GUIDED, arm, set-points, its HEARTBEATs) recorded off
  its link, the person parks the rover, the autopilot reboots on the same storage (its signing key and saved
  timestamp) and the recording is sent again on the same port, soon after the recording and again more than a
  minute after it. What ArduPilot does (libraries/GCS_MAVLink/GCS_Signing.cpp and the C library's
  ``mavlink_signature_check``): at boot its timestamp is the saved one plus a minute, the GPS's UTC raises it and
  saves it at once, and a new stream is taken when at most a minute behind it. So a recording is taken as a new
  stream while it is less than a minute old and signed after the last save; docs/SECURITY.md says what follows.

Each row boots SITL at real time (speedup 1: SITL's GPS time then follows the wall clock, as a real GPS does; a
faster boot runs its GPS clock ahead of the wall and hides the window). Rows return ``{"reached_vehicle": ...,
"ok": bool, ...}`` as bench/attack.py's do.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

from bench.attack_rigs import Result

#: the host's component on the driver's link (a companion computer's), not the pilot's (a ground station's)
HOST_COMPONENT = 191


class _Recorder:
    """Stands for a pymavlink connection's file: what is written goes to the link and into :attr:`frames`."""

    def __init__(self, file: Any) -> None:
        self.file, self.frames = file, []

    def write(self, data: bytes) -> None:
        self.frames.append((time.monotonic(), bytes(data)))
        self.file.write(data)


def _replay(url: str, frames: list[tuple[float, bytes]]) -> None:
    """``frames`` sent again to ``url`` (``tcp:HOST:PORT``) from a connection of their own, in their order, at
    most 20 ms apart (the recording's gaps shortened: its resends and set-points, not its pauses)."""
    host, port = url.split(":")[1:]
    with socket.create_connection((host, int(port)), timeout=5.0) as s:
        last = None
        for t, data in frames:
            if last is not None:
                time.sleep(min(0.02, max(0.0, t - last)))
            last = t
            s.sendall(data)
        time.sleep(0.5)  # the vehicle reads what is buffered before the connection closes (SITL drops the rest)


def _record_takeover(sitl: Any, key: bytes) -> tuple[_Recorder, bool]:
    """A host on ``sitl``'s driver port, signing with ``key``, takes the rover (GUIDED, armed, 1.5 s of 0.5 m/s
    set-points at 10 Hz) while its frames are recorded; then it closes. The recording, and whether the pilot saw the
    rover taken (GUIDED, armed, moving) before the host closed."""
    from sim_learner.sitl import Pilot

    host = Pilot(sitl.driver_url, source_system=255, source_component=HOST_COMPONENT)
    try:
        host.sign_with(key)
        rec = _Recorder(host.conn.mav.file)
        host.conn.mav.file = rec
        host.set_mode("GUIDED")
        host.arm(True)
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            host.velocity(0.5, 0.0)
            time.sleep(0.1)
        took = sitl.pilot.wait(lambda s: s.armed and s.mode == "GUIDED", 3.0) and sitl.pilot.speed > 0.1
    finally:
        host.close()
    return rec, took


def replay_after_reboot(binary: str, replay_after_s: float, park: bool = True, speedup: float = 1.0) -> dict:
    """One run: SITL booted with a signing key set by the pilot; a host on the driver's port, signing with it, takes
    the rover (GUIDED, armed, 0.5 m/s for 1.5 s) while its frames are recorded; the pilot parks it (HOLD, disarmed;
    ``park`` False: it loses power armed); SITL reboots on the same storage; ``replay_after_s`` s after the
    recording ended (or as soon as it has booted, if later) the recording goes to the driver's port again. What
    the pilot then sees."""
    import os

    from sim_learner.sitl import Sitl

    key = os.urandom(32)
    with Sitl(binary, boot_speedup=speedup, keep_dir=False) as sitl:
        assert sitl.pilot is not None
        sitl.pilot.setup_signing(key)
        rec, took = _record_takeover(sitl, key)
        recorded_at = time.monotonic()
        if park:
            sitl.pilot.set_mode("HOLD")
            sitl.pilot.arm(False)
        t_reboot = time.monotonic()
        sitl.reboot()
        booted_s = round(time.monotonic() - t_reboot, 1)
        pilot = sitl.pilot
        assert pilot is not None
        wait = recorded_at + replay_after_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        age = round(time.monotonic() - recorded_at, 1)
        before = {"mode": pilot.mode, "armed": pilot.armed}
        _replay(sitl.driver_url, rec.frames)
        armed = pilot.wait(lambda s: s.armed, 3.0)
        guided = pilot.wait(lambda s: s.mode == "GUIDED", 0.5)
        texts = pilot.texts()[-4:]
        speed = pilot.speed
    return {"recording_took_the_rover": took, "parked": park, "frames": len(rec.frames), "reboot_boot_s": booted_s,
            "replayed_after_s": age, "before_replay": before,
            "after_replay": {"armed": armed, "mode": "GUIDED" if guided else pilot.mode, "speed_m_s": round(speed, 3)},
            "vehicle_said": texts, "ok": took and not armed and not guided}


def sitl_replay_after_reboot(short: bool) -> Result:
    """The recording sent again soon after the reboot (it has booted) and, in another run, more than a minute
    after it was made: ArduPilot takes the first (it is a new stream within a minute of its timestamp and signed
    after the last save) and refuses the second. ``ok`` is that the old recording is refused; the soon one is
    reported, not judged (what remains, docs/SECURITY.md)."""
    from sim_learner.sitl import find_sitl

    binary = find_sitl()
    if binary is None:
        return {"reached_vehicle": None, "learned": None, "ok": False, "error": "no SITL binary"}
    soon = replay_after_reboot(str(binary), 0.0)
    old = replay_after_reboot(str(binary), 65.0)
    return {"reached_vehicle": {"soon": soon["after_replay"], "after_a_minute": old["after_replay"]},
            "learned": None, "soon": soon, "after_a_minute": old,
            "ok": old["recording_took_the_rover"] and old["ok"]}


def replay_into_fresh(binary: str, speedup: float = 1.0) -> dict:
    """The control: the same recording sent to a second SITL (its own storage) given the key just after the
    recording was made, never rebooted: whether the replay path itself takes a rover."""
    import os

    from sim_learner.sitl import Sitl

    key = os.urandom(32)
    with Sitl(binary, boot_speedup=speedup) as first:
        assert first.pilot is not None
        first.pilot.setup_signing(key)
        rec, _ = _record_takeover(first, key)
    recorded_at = time.monotonic()
    with Sitl(binary, boot_speedup=speedup) as second:
        assert second.pilot is not None
        second.pilot.setup_signing(key)
        age = round(time.monotonic() - recorded_at, 1)
        _replay(second.driver_url, rec.frames)
        armed = second.pilot.wait(lambda s: s.armed, 3.0)
        return {"replayed_after_s": age, "armed": armed, "mode": second.pilot.mode,
                "vehicle_said": second.pilot.texts()[-4:]}


#: the driver host's system id in the host-killed runs: the one the GCS failsafe watches (MAV_GCS_SYSID), not the
#: person's ground station's (255)
HOST_SYSID = 245


def host_killed(binary: str, params: dict[str, float], speedup: float = 10.0) -> dict:
    """A host on the driver's port (system :data:`HOST_SYSID`, HEARTBEATs at 10 Hz) takes the rover (GUIDED, armed,
    0.5 m/s set-points at 10 Hz) and dies without a word (its connection closed, as a SIGKILL closes it). From its
    last message: when the pilot sees the rover stopped (below 0.05 m/s), in which mode, armed or not, and what it
    said. ``params``: SITL's defaults for this run (e.g. the GCS failsafe's)."""
    from sim_learner.sitl import MAV, Pilot, Sitl

    with Sitl(binary, boot_speedup=speedup, params=params) as sitl:
        pilot = sitl.pilot
        assert pilot is not None
        got = {k: pilot.param(k) for k in params}
        host = Pilot(sitl.driver_url, source_system=HOST_SYSID, source_component=HOST_COMPONENT)
        try:
            host.set_mode("GUIDED")
            host.arm(True)
            t_end = time.monotonic() + 3.0
            while time.monotonic() < t_end:
                host.send("heartbeat", MAV.MAV_TYPE_ONBOARD_CONTROLLER, MAV.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                host.velocity(0.5, 0.0)
                time.sleep(0.1)
            driving = pilot.speed
        finally:
            t_dead = time.monotonic()
            host.close()
        stopped = pilot.wait(lambda s: bool(s.samples) and s.samples[-1].t > t_dead and s.samples[-1].speed < 0.05,
                             8.0)
        after = [s for s in pilot.samples(t_dead) if s.speed < 0.05]
        t_stop = round(after[0].t - t_dead, 2) if stopped and after else None
        time.sleep(0.3)
        return {"params": got, "speed_before": round(driving, 3), "stopped_after_s": t_stop, "mode": pilot.mode,
                "armed": pilot.armed, "vehicle_said": [t for t in pilot.texts()[-6:] if "PreArm" not in t]}


def sitl_host_killed(short: bool) -> Result:
    """A keyed host drives the rover in GUIDED at 0.5 m/s and dies without a word (as a SIGKILLed driver host),
    with Rover's defaults (only GUIDED's 3 s target timeout stops it) and with the GCS failsafe watching the host
    (FS_GCS_ENABLE 1, FS_ACTION 2 Hold, FS_GCS_TIMEOUT 0.5, MAV_GCS_SYSID the host's, HEARTBEATs at 10 Hz; FS_TIMEOUT
    left at 1.5 s: SITL's failsafe fired while the host was alive with 0.3 s). ``ok``: the failsafe stops it sooner,
    in HOLD. Neither ends within the host's deadman: docs/SECURITY.md says what remains."""
    from sim_learner.sitl import find_sitl

    binary = find_sitl()
    if binary is None:
        return {"reached_vehicle": None, "learned": None, "ok": False, "error": "no SITL binary"}
    default = host_killed(str(binary), {"FS_GCS_ENABLE": 0})
    watched = host_killed(str(binary), {"FS_GCS_ENABLE": 1, "FS_GCS_TIMEOUT": 0.5, "FS_ACTION": 2,
                                        "MAV_GCS_SYSID": HOST_SYSID})
    a, b = default["stopped_after_s"], watched["stopped_after_s"]
    return {"reached_vehicle": {"stopped_after_s": {"guided_timeout": a, "gcs_failsafe": b}}, "learned": None,
            "guided_timeout": default, "gcs_failsafe": watched,
            "ok": a is not None and b is not None and b < a and watched["mode"] == "HOLD"}


SITL_ATTACKS: dict[str, Callable[[bool], Result]] = {
    f.__name__: f for f in (sitl_replay_after_reboot, sitl_host_killed)}

__all__ = ["SITL_ATTACKS", "host_killed", "replay_after_reboot", "replay_into_fresh"]
