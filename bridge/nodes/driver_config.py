"""The driver host's configuration: its own ``[driver]`` section and one ``[link.<name>]`` section per registered link.

It sits with the driver host (layer 3) rather than in :mod:`bridge.core.config` because its link sections are the
links' own configuration structs, which live in their modules under ``drivers/`` (layer 2): :class:`LinkSection` is
built from :data:`drivers.LINKS`, one optional table per link defaulting to that link's ``CONFIG``, so a link added to
the registry is a section here with nothing else to edit. Decoding and its one-line errors are
:mod:`bridge.core.config`'s.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from msgspec import Meta, field

import drivers
from bridge.core.config import BoundsConfig, Cfg, RobotName, Rule, load, meta
from bridge.core.limiter import AxisLimiter, SpeedLimiter

SourceName = Annotated[str, Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="a non-blank source name")]
#: hard limits beyond these are a mistake, not a vehicle (m/s, rad/s)
HARD_V_MAX, HARD_W_MAX = 20.0, 20.0

#: the largest acceleration (m/s², rad/s²) and jerk (m/s³, rad/s³) limit taken as a vehicle's, not a typo
HARD_ACCEL_MAX, HARD_JERK_MAX = 1000.0, 100000.0


def _rate_limit(what: str, top: float) -> Meta:
    return meta(f"{what}; unset: unlimited (the speed limiter, bridge.core.limiter)", gt=0.0, le=top)


class HardLimits(BoundsConfig):
    """``[driver.hard_limits]``: the command box, and how fast each axis may change (the robot-side speed limiter)."""

    v_accel: Annotated[float, _rate_limit("largest change of v the vehicle gets, m/s²", HARD_ACCEL_MAX)] | None = None
    omega_accel: Annotated[float, _rate_limit("largest change of omega, rad/s²", HARD_ACCEL_MAX)] | None = None
    v_jerk: Annotated[float, _rate_limit("largest change of v's acceleration, m/s³", HARD_JERK_MAX)] | None = None
    omega_jerk: Annotated[float, _rate_limit("largest change of omega's acceleration, rad/s³",
                                             HARD_JERK_MAX)] | None = None

    def limiter(self, period: float) -> SpeedLimiter:
        """The speed limiter these limits make (an unset one: that axis unlimited) for a host ticking each ``period``
        s (a stalled loop's step is bounded by two periods' worth)."""
        return SpeedLimiter(AxisLimiter(self.v_accel, self.v_jerk), AxisLimiter(self.omega_accel, self.omega_jerk),
                            period=period)


DEFAULT_HARD_LIMITS = HardLimits(v=(-0.5, 0.5), w=(-1.0, 1.0))


class DriverSection(Cfg):
    """``[driver]``: the driver host's loop and safety settings."""

    rate_hz: Annotated[float, meta("control loop rate, Hz", ge=1.0, le=1000.0)] = 50.0
    cmd_timeout: Annotated[float, meta("deadman: no valid command for this long stops the vehicle, s", ge=0.02,
                                       le=10.0)] = 0.3
    hard_limits: Annotated[HardLimits, meta("every command is clamped into this box, and its changes are limited, "
                                            "before a vehicle sees it")] = DEFAULT_HARD_LIMITS
    max_send_hz: Annotated[float, meta("the most commands per second handed to the link (a command is sent as it "
                                       "arrives; two may follow each other at once, then 1/max_send_hz apart: over "
                                       "T seconds at most 2 + max_send_hz * T)", ge=1.0, le=1000.0)] = 100.0
    max_telemetry_age_s: Annotated[float, meta("no pose from the link for this long stops the vehicle (it would drive "
                                               "blind), s", gt=0.0, le=60.0)] = 0.5
    estop_release_sources: Annotated[tuple[SourceName, ...],
                                     meta("Estop sources allowed to release a latched estop (scmbridge estop "
                                          "--release --source NAME); at least one", min_length=1)] = ("operator",)

    pose_source: Annotated[Literal["link", "mocap"], meta(
        "where the published state comes from: the link's own telemetry, or a motion-capture bridge publishing "
        "scm/<robot>/mocap (restamped onto this host's clock)")] = "link"
    mocap_window_s: Annotated[float, meta("mocap: the clock-offset estimate is the least (receipt - stamp) over this "
                                          "window, s", gt=0.1, le=600.0)] = 5.0
    engage_on_start: Annotated[bool, meta(
        "engage the vehicle when the host starts (MAVLink: select GUIDED and arm; CAN: closed loop). Off: the host "
        "waits for a person (scmbridge engage, or the operator selecting GUIDED and arming), also after a restart")] = (
        False)
    stop_speed: Annotated[float, meta("closing: zero commands until the vehicle reports less than this, then disarm, "
                                      "m/s", gt=0.0, le=5.0)] = 0.05
    stop_timeout: Annotated[float, meta("closing: the longest wait for the vehicle to stop before disarming, s", gt=0.0,
                                        le=60.0)] = 3.0
    max_drive_on_s: Annotated[float, meta(
        "warn when the vehicle's own failsafe lets it drive on longer than this after the host dies, s", gt=0.0,
        le=600.0)] = 1.0

    def __post_init__(self) -> None:
        if self.max_send_hz < self.rate_hz:
            raise Rule(f"max_send_hz = {self.max_send_hz} is below rate_hz = {self.rate_hz}: every tick sends")
        (v_lo, v_hi), (w_lo, w_hi) = self.hard_limits.v, self.hard_limits.w
        if max(abs(v_lo), abs(v_hi)) > HARD_V_MAX or max(abs(w_lo), abs(w_hi)) > HARD_W_MAX:
            raise Rule(f"hard_limits v = [{v_lo}, {v_hi}], w = [{w_lo}, {w_hi}] are beyond any rover this drives "
                       f"(|v| <= {HARD_V_MAX} m/s, |w| <= {HARD_W_MAX} rad/s): a typo would let anything through")


def _registered() -> tuple[tuple[str, type], ...]:
    """(name, config struct) of every link registered now."""
    return tuple((name, drivers.link_config(name)) for name in drivers.LINKS)


def link_section(links: tuple[tuple[str, type], ...]) -> type[Cfg]:
    """``[link.<name>]`` for each of ``links`` (name, config struct): one optional table each, decoded into (and
    defaulting to) the link's own configuration struct."""
    fields = [(name, config, field(default_factory=config)) for name, config in links]
    section = msgspec.defstruct("LinkSection", fields, bases=(Cfg,), module=__name__)
    section.__doc__ = "``[link.<name>]``: the settings of each link this driver host may use (``--link`` picks one)."
    return section


#: the links :class:`LinkSection` was built from: those registered when this module was imported
_BUILT_FROM = _registered()
LinkSection = link_section(_BUILT_FROM)


class DriverConfig(Cfg):
    """A driver host's configuration file."""

    robot: RobotName = "learner"
    driver: DriverSection = field(default_factory=DriverSection)
    link: LinkSection = field(default_factory=LinkSection)


@functools.cache
def _config_for(links: tuple[tuple[str, type], ...]) -> type[DriverConfig]:
    """:class:`DriverConfig` itself for the links it was built from, else a subclass whose ``link`` holds the
    sections of ``links``."""
    if links == _BUILT_FROM:
        return DriverConfig
    section = link_section(links)
    return msgspec.defstruct("DriverConfig", [("link", section, field(default_factory=section))], bases=(DriverConfig,),
                             module=__name__)


def driver_config_type() -> type[DriverConfig]:
    """:class:`DriverConfig` for the links registered now: a link added to :data:`drivers.LINKS` after this module was
    imported gets its section too."""
    return _config_for(_registered())


def load_driver(path: str | Path | None) -> DriverConfig:
    """The driver host's configuration in ``path`` (the defaults when None), or :class:`ConfigError`."""
    return load(path, driver_config_type())


__all__ = ["DEFAULT_HARD_LIMITS", "DriverConfig", "DriverSection", "HardLimits", "LinkSection", "driver_config_type",
           "link_section", "load_driver"]
