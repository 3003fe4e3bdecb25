"""``scmbridge doctor --link mavlink``'s look at a real ArduPilot Rover: what the project relies on, each with its fix.

Over the driver's own link and ids (:class:`drivers.mavlink.probe.Probe`: reads only; the vehicle's mode, arming and
parameters are never changed), one line each:

- ``guided``: the vehicle is an ArduPilot Rover (its HEARTBEAT), whose GUIDED mode the driver host drives in, and
  where a person takes it back: an RC mode-switch position set to HOLD (``MODE1`` .. ``MODE6``);
- ``gcs-fs``: the ground-station failsafe (``FS_GCS_ENABLE``, ``FS_GCS_TIMEOUT``, ``FS_ACTION``) and whose heartbeat
  it watches (``MAV_GCS_SYSID``, formerly ``SYSID_MYGCS``): this host's, or the ground station's when it speaks as a
  companion computer; the RC failsafe (``FS_THR_ENABLE``);
- ``guided-to``: GUIDED's own timeout: Rover stops a velocity target not renewed within 3 s (not a parameter; the
  driver host's deadman stops it long before);
- ``signing``: the vehicle signs its messages with the key ``signing_key_file`` names (MAVLink 2 signing on);
- ``arming``: the arming checks are on (``ARMING_CHECK``, or ``ARMING_SKIPCHK`` on newer firmware), arming is
  required (``ARMING_REQUIRE``), and whether the pre-arm checks pass now (SYS_STATUS);
- ``range``: the parameters the station's learner range comes from (``WP_SPEED``, ``CRUISE_SPEED``,
  ``ATC_STR_RAT_MAX``; deploy/station.example.toml), the range they give, and the driver's ``hard_limits`` against it.

docs/OPERATING.md, "First day with your rover", says when to run it (before the driver host starts: a serial port
opens once).
"""

from __future__ import annotations

import math

from bridge.tools.doctor import Check

#: the parameters read, the old and the new name of each where ArduPilot renamed one
PARAMS = ("FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_ACTION", "FS_TIMEOUT", "FS_THR_ENABLE", "MAV_GCS_SYSID", "SYSID_MYGCS",
          "ARMING_CHECK", "ARMING_SKIPCHK", "ARMING_REQUIRE", "WP_SPEED", "CRUISE_SPEED", "ATC_STR_RAT_MAX", "MODE_CH",
          *(f"MODE{k}" for k in range(1, 7)))
#: s for the vehicle's HEARTBEAT, and for its parameters
HEARD_S, PARAMS_S = 5.0, 4.0
#: MAV_SYS_STATUS_PREARM_CHECK (SYS_STATUS's sensor bits): the pre-arm checks, and whether they pass
PREARM_BIT = 0x10000000


def _modes() -> dict[int, str]:
    from drivers.mavlink.dialect import load_pymavlink

    return dict(load_pymavlink().modes.names)


def check_guided(probe, p: dict[str, float]) -> list[Check]:
    mav = probe.d.mav
    hb = probe.heartbeat
    if hb.autopilot != mav.MAV_AUTOPILOT_ARDUPILOTMEGA or hb.type not in (mav.MAV_TYPE_GROUND_ROVER,
                                                                          mav.MAV_TYPE_SURFACE_BOAT):
        return [Check("FAIL", "guided", f"the vehicle is not an ArduPilot Rover (HEARTBEAT type {hb.type}, autopilot "
                                        f"{hb.autopilot}): the MAVLink link drives Rover's GUIDED mode; check "
                                        "target_system/target_component")]
    names = _modes()
    out = [Check("ok", "guided", f"ArduPilot Rover, mode {names.get(hb.custom_mode, hb.custom_mode)}: GUIDED is "
                                 "its mode for a companion's set-points (engage: the GCS or scmbridge engage)")]
    positions = [k for k in range(1, 7) if p.get(f"MODE{k}") == 4]  # Rover's HOLD
    if positions:
        out.append(Check("ok", "rc-hold", f"the RC mode switch (channel {p.get('MODE_CH', 8):g}) has HOLD at "
                                          f"position {positions[0]}: a person takes the rover with the transmitter"))
    elif any(f"MODE{k}" in p for k in range(1, 7)):
        out.append(Check("warn", "rc-hold", "no RC mode-switch position is HOLD: set one (MODE1..MODE6 = 4) so a "
                                            "person can stop the rover from the transmitter whatever the link does"))
    return out


def check_gcs_failsafe(config, p: dict[str, float]) -> list[Check]:
    out = []
    gcs_id = p.get("MAV_GCS_SYSID", p.get("SYSID_MYGCS"))
    watched = ("this host's heartbeat" if gcs_id == config.source_system else
               f"system {gcs_id:g}'s heartbeat (the ground station), not this host's" if gcs_id is not None else
               "the ground station's heartbeat")
    enable, action = p.get("FS_GCS_ENABLE"), p.get("FS_ACTION")
    if enable is None:
        out.append(Check("warn", "gcs-fs", "FS_GCS_ENABLE did not answer: the GCS failsafe is unknown"))
    elif enable == 0:
        out.append(Check("warn", "gcs-fs", f"the GCS failsafe is off (FS_GCS_ENABLE 0): a lost ground link goes on "
                                           f"unnoticed by the vehicle; fix: FS_GCS_ENABLE 1, FS_ACTION 2 (Hold), "
                                           f"FS_GCS_TIMEOUT 5 (it watches {watched})"))
    elif not action:
        out.append(Check("warn", "gcs-fs", "FS_GCS_ENABLE is on but FS_ACTION 0 does nothing: fix: FS_ACTION 2 (Hold)"))
    elif gcs_id == config.source_system and p.get("FS_GCS_TIMEOUT", math.inf) <= 2.0 / config.heartbeat_hz:
        out.append(Check("warn", "gcs-fs", f"the GCS failsafe watches this host with FS_GCS_TIMEOUT "
                                           f"{p['FS_GCS_TIMEOUT']:g} s, within two of its HEARTBEATs ([link.mavlink] "
                                           f"heartbeat_hz {config.heartbeat_hz:g}): it holds the rover while this host "
                                           f"drives it; fix: heartbeat_hz = {min(20.0, 4.0 / p['FS_GCS_TIMEOUT']):g}"))
    else:
        out.append(Check("ok", "gcs-fs", f"GCS failsafe on: FS_ACTION {action:g} after FS_GCS_TIMEOUT "
                                         f"{p.get('FS_GCS_TIMEOUT', math.nan):g} s without {watched}"))
    thr = p.get("FS_THR_ENABLE")
    if thr == 0:
        out.append(Check("warn", "rc-fs", "the RC failsafe is off (FS_THR_ENABLE 0): a transmitter out of range is not "
                                          "noticed; fix: FS_THR_ENABLE 1"))
    elif thr is not None:
        out.append(Check("ok", "rc-fs", f"RC failsafe on (FS_THR_ENABLE {thr:g}, FS_ACTION {action or 0:g})"))
    return out


def check_guided_timeout(driver_cfg) -> Check:
    from drivers.mavlink.state import GUIDED_TIMEOUT_S

    deadman = driver_cfg.driver.cmd_timeout
    if deadman < GUIDED_TIMEOUT_S:
        return Check("ok", "guided-to", f"GUIDED stops a velocity target not renewed within {GUIDED_TIMEOUT_S:g} s "
                                        f"(Rover, not a parameter); the host's deadman, cmd_timeout {deadman:g} s, "
                                        "stops it first")
    return Check("warn", "guided-to", f"cmd_timeout {deadman:g} s is not shorter than GUIDED's own "
                                      f"{GUIDED_TIMEOUT_S:g} s: fix: [driver] cmd_timeout = 0.3")


def check_signing(probe, config) -> Check:
    if not config.signing_key_file:
        if probe.carrying_signature:
            return Check("warn", "signing", "the vehicle signs its messages but signing_key_file is empty: name its "
                                            "key in [link.mavlink] signing_key_file (the driver host refuses nothing "
                                            "and signs nothing without it)")
        return Check("warn", "signing", "MAVLink signing is off (the vehicle's messages carry no signature): fix: "
                                        "scmbridge keys mavlink --robot R --passphrase WORD --install --driver FILE, "
                                        "then signing_key_file")
    if probe.signed_from_vehicle:
        return Check("ok", "signing", f"on: the vehicle's messages verify with {config.signing_key_file}")
    bad = probe.conn.mav.signing.badsig_count
    if probe.carrying_signature or bad:
        return Check("FAIL", "signing", f"the vehicle signs with another key than {config.signing_key_file}: fix: "
                                        "install this one (scmbridge keys mavlink --install --old-key OLD) or name "
                                        "the vehicle's")
    return Check("FAIL", "signing", "the vehicle does not sign (it has no key): fix: scmbridge keys mavlink --robot R "
                                    f"--out {config.signing_key_file} --passphrase WORD --install --driver FILE")


def check_arming(probe, p: dict[str, float]) -> list[Check]:
    out = []
    if "ARMING_SKIPCHK" in p:
        off = p["ARMING_SKIPCHK"] != 0
        what = f"ARMING_SKIPCHK {p['ARMING_SKIPCHK']:g}"
        fix = "ARMING_SKIPCHK 0"
    elif "ARMING_CHECK" in p:
        off = p["ARMING_CHECK"] != 1
        what = f"ARMING_CHECK {p['ARMING_CHECK']:g}"
        fix = "ARMING_CHECK 1"
    else:
        off, what, fix = None, "", ""
    if off is None:
        out.append(Check("warn", "arming", "the arming-check parameter did not answer"))
    elif off:
        out.append(Check("warn", "arming", f"some arming checks are skipped ({what}): fix: {fix} (all checks)"))
    else:
        out.append(Check("ok", "arming", f"every arming check on ({what})"))
    if p.get("ARMING_REQUIRE") == 0:
        out.append(Check("warn", "arming", "ARMING_REQUIRE 0: the vehicle is armed from boot; fix: ARMING_REQUIRE 1"))
    st = probe.sys_status
    if st is not None and st.onboard_control_sensors_present & PREARM_BIT:
        if st.onboard_control_sensors_health & PREARM_BIT:
            out.append(Check("ok", "prearm", "the pre-arm checks pass now"))
        else:
            said = [t for t in probe.texts if t.startswith("PreArm")][-2:]
            out.append(Check("warn", "prearm", "the pre-arm checks fail now" + (f": {'; '.join(said)}" if said else
                                                                              " (the ground station says why)")))
    return out


def check_range(p: dict[str, float], driver_cfg, station_cfg=None) -> list[Check]:
    from bridge.core.errors import UsageError
    from bridge.tools.demo_sitl import learner_range

    if not all(n in p for n in ("WP_SPEED", "CRUISE_SPEED", "ATC_STR_RAT_MAX")):
        return [Check("warn", "range", "WP_SPEED, CRUISE_SPEED or ATC_STR_RAT_MAX did not answer: the learner range "
                                       "cannot be read from the vehicle")]
    try:
        (v_lo, v_hi), (w_lo, w_hi) = learner_range(p)
    except UsageError as exc:
        return [Check("FAIL", "range", str(exc))]
    src = (f"WP_SPEED {p['WP_SPEED']:g}, CRUISE_SPEED {p['CRUISE_SPEED']:g}, ATC_STR_RAT_MAX "
           f"{p['ATC_STR_RAT_MAX']:g}")
    out = [Check("ok", "range", f"{src}: the learner's range is v = [{v_lo:g}, {v_hi:.4g}], w = [{w_lo:.4f}, "
                                f"{w_hi:.4f}] ([learner_bounds] in station.toml)")]
    hard = driver_cfg.driver.hard_limits
    if hard.v[1] > v_hi + 1e-9 or max(-hard.w[0], hard.w[1]) > w_hi + 1e-9:
        out.append(Check("warn", "range", f"[driver.hard_limits] v = {list(hard.v)}, w = {list(hard.w)} are wider than "
                                          f"the vehicle's ({src}): fix: hard_limits no wider than v = [-{v_hi:.4g}, "
                                          f"{v_hi:.4g}], w = [{w_lo:.4f}, {w_hi:.4f}]"))
    if station_cfg is not None:
        lb = station_cfg.learner_bounds
        if abs(lb.v[1] - v_hi) > 0.01 or abs(lb.w[1] - w_hi) > 0.01:
            out.append(Check("warn", "range", f"the station's [learner_bounds] v = {list(lb.v)}, w = {list(lb.w)} are "
                                              f"not the vehicle's ({src}): fix: v = [{v_lo:g}, {v_hi:.4g}], "
                                              f"w = [{w_lo:.4f}, {w_hi:.4f}]"))
    return out


def check_mavlink(driver_cfg, station_cfg=None) -> list[Check]:
    """Every check above, over ``driver_cfg``'s ``[link.mavlink]`` (never engaged)."""
    from bridge.core.auth import KeyFileError, load_key
    from drivers.mavlink.client import verify_before_recording
    from drivers.mavlink.probe import Probe

    config = driver_cfg.link.mavlink
    try:
        probe = Probe(config)
    except Exception as exc:  # pymavlink raises OSError, SerialException, ...
        return [Check("FAIL", "mavlink", f"cannot open {config.url}: {exc} (stop the driver host first: a serial port "
                                         "opens once)")]
    try:
        if config.signing_key_file:
            try:
                key = load_key(config.signing_key_file, "mavlink")
            except KeyFileError as exc:
                return [Check("FAIL", "signing", str(exc))]
            probe.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda *_: True)
            verify_before_recording(probe.conn.mav)
        if not probe.wait(lambda: probe.heartbeat is not None, HEARD_S):
            return [Check("FAIL", "mavlink", f"no HEARTBEAT from system {config.target_system} component "
                                             f"{config.target_component} on {config.url} within {HEARD_S:g} s: check "
                                             "url, baud and the ids")]
        p = probe.read_params(PARAMS, PARAMS_S)
        probe.wait(lambda: probe.sys_status is not None and probe.heartbeats >= 2, 2.0)
        return [*check_guided(probe, p), *check_gcs_failsafe(config, p), check_guided_timeout(driver_cfg),
                check_signing(probe, config), *check_arming(probe, p), *check_range(p, driver_cfg, station_cfg)]
    finally:
        probe.close()
