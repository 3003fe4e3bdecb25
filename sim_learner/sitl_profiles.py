"""A seeded family of ArduPilot Rover parameter profiles: vehicles the project never tuned for, as a lab's rover
would be (docs/BENCHMARKS.md "The transfer on SITL", ``scmbridge bench sitl``).

Each profile is an extra parameter file for SITL's ``rover-skid`` (skid steering) or ``rover`` (Ackermann) body,
drawn over the parameters that shape a rover's response to GUIDED's velocity and turn-rate set-points (names and
ranges as ArduPilot documents them: libraries/APM_Control/AR_AttitudeControl.cpp, libraries/AR_Motors/
AP_MotorsUGV.cpp, Rover/Parameters.cpp):

- ``WP_SPEED`` (0-100 m/s; GUIDED caps its speed target there): set below the teacher's top speed, or left at the
  frame's default (SITL's rover-skid.parm 3 m/s, rover.parm 5 m/s: a range read from it is far too wide);
- ``CRUISE_SPEED`` / ``CRUISE_THROTTLE`` (0-100 m/s, 0-100 %): the throttle feed-forward's tuning point, drawn so that
  the open-loop speed is a share of the command (the frame's stock pair is what its body reaches);
- ``ATC_SPEED_P`` (0.01-2), ``ATC_SPEED_I`` (0-2), ``ATC_SPEED_FF`` (0-0.5): the speed loop, weak or open;
- ``ATC_ACCEL_MAX`` / ``ATC_DECEL_MAX`` (0-10 m/s/s; 0: no ramp, DECEL 0: ACCEL's);
- ``ATC_STR_RAT_MAX`` (0-1000 deg/s): the turn-rate cap, at most the teacher's 45 deg/s;
- ``ATC_STR_RAT_P`` (0-2), ``ATC_STR_RAT_I`` (0-2), ``ATC_STR_RAT_FF`` (0-3): the turn-rate loop, weak or open,
  its feed-forward mistuned around the frame's stock value;
- ``MOT_THST_EXPO`` (-1 to 1): a thrust curve the motors do not have.

The family is fixed by its seed: profile ``k`` of a frame is the same on every machine, and so is the split into a
development half (what the method may be tuned on) and a held-out half (what it is judged on).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

#: the family's seed (the split between the halves follows from it too)
SEED = 20261205
#: profiles per frame (half development, half held out)
COUNT = 24
#: the frames: our name -> SITL's ``--model``
FRAMES = {"skid": "rover-skid", "ackermann": "rover"}
#: each frame's stock throttle feed-forward pair (CRUISE_THROTTLE % for CRUISE_SPEED m/s: SITL's default_params) and
#: its stock turn-rate feed-forward
STOCK = {"skid": {"CRUISE_SPEED": 3.0, "CRUISE_THROTTLE": 75.0, "ATC_STR_RAT_FF": 0.2},
         "ackermann": {"CRUISE_SPEED": 5.0, "CRUISE_THROTTLE": 30.0, "ATC_STR_RAT_FF": 0.75}}
#: ArduPilot's documented range of each parameter drawn here (a profile never leaves it)
RANGES = {"WP_SPEED": (0.0, 100.0), "CRUISE_SPEED": (0.0, 100.0), "CRUISE_THROTTLE": (0.0, 100.0),
          "ATC_SPEED_P": (0.01, 2.0), "ATC_SPEED_I": (0.0, 2.0), "ATC_SPEED_FF": (0.0, 0.5),
          "ATC_ACCEL_MAX": (0.0, 10.0), "ATC_DECEL_MAX": (0.0, 10.0), "ATC_STR_RAT_MAX": (0.0, 1000.0),
          "ATC_STR_RAT_P": (0.0, 2.0), "ATC_STR_RAT_I": (0.0, 2.0), "ATC_STR_RAT_FF": (0.0, 3.0),
          "MOT_THST_EXPO": (-1.0, 1.0)}


@dataclass(frozen=True)
class Profile:
    """One vehicle of the family: its frame, index, half (``dev`` or ``heldout``) and parameters."""

    frame: str
    index: int
    split: str
    params: dict[str, float] = field(hash=False)

    @property
    def name(self) -> str:
        return f"{self.frame}-{self.index:02d}"

    @property
    def model(self) -> str:
        return FRAMES[self.frame]

    def parm(self) -> str:
        """The profile as an ArduPilot parameter file (what ``--sitl-params`` reads)."""
        head = (f"# {self.name} ({self.split}): a generated ArduPilot Rover profile for SITL's {self.model} "
                f"(sim_learner/sitl_profiles.py, seed {SEED})\n")
        if "WP_SPEED" not in self.params:
            head += "# WP_SPEED left at the frame's default\n"
        return head + "".join(f"{k} {_fmt(v)}\n" for k, v in self.params.items())


def _fmt(v: float) -> str:
    return f"{v:.3f}".rstrip("0").rstrip(".") if v != int(v) else str(int(v))


def _draw(frame: str, rng: np.random.Generator) -> dict[str, float]:
    stock = STOCK[frame]
    p: dict[str, float] = {}
    if rng.random() < 0.5:
        p["WP_SPEED"] = round(float(rng.uniform(0.3, 0.6)), 2)
    cruise = round(float(stock["CRUISE_SPEED"] * rng.uniform(0.5, 1.5)), 2)
    share = rng.uniform(0.55, 1.0)  # the open-loop speed's share of the command
    p["CRUISE_SPEED"] = cruise
    p["CRUISE_THROTTLE"] = round(float(min(95.0, stock["CRUISE_THROTTLE"] / stock["CRUISE_SPEED"] * cruise * share)),
                                 1)
    p["ATC_SPEED_P"] = round(float(rng.uniform(0.01, 0.3)), 3)
    p["ATC_SPEED_I"] = 0.0 if rng.random() < 0.5 else round(float(rng.uniform(0.0, 0.3)), 3)
    p["ATC_SPEED_FF"] = round(float(rng.uniform(0.0, 0.2)), 3)
    p["ATC_ACCEL_MAX"] = 0.0 if rng.random() < 0.4 else round(float(rng.uniform(0.5, 3.0)), 2)
    p["ATC_DECEL_MAX"] = 0.0 if rng.random() < 0.5 else round(float(rng.uniform(0.5, 3.0)), 2)
    p["ATC_STR_RAT_MAX"] = round(float(rng.uniform(20.0, 45.0)), 1)
    p["ATC_STR_RAT_P"] = round(float(rng.uniform(0.0, 0.2)), 3)
    p["ATC_STR_RAT_I"] = 0.0 if rng.random() < 0.5 else round(float(rng.uniform(0.0, 0.2)), 3)
    p["ATC_STR_RAT_FF"] = round(float(stock["ATC_STR_RAT_FF"] * rng.uniform(0.6, 2.0)), 3)
    p["MOT_THST_EXPO"] = round(float(rng.uniform(-0.5, 0.5)), 2)
    return p


def family(frame: str, count: int = COUNT, seed: int = SEED) -> list[Profile]:
    """The frame's ``count`` profiles: profile k drawn from its own generator (so a longer family keeps the first
    ones), half of them held out by a permutation fixed by ``seed``."""
    if frame not in FRAMES:
        raise ValueError(f"frame {frame!r}: one of {', '.join(FRAMES)}")
    salt = list(FRAMES).index(frame)
    held = set(np.random.default_rng([seed, salt, 1]).permutation(count)[: count // 2].tolist())
    return [Profile(frame, k, "heldout" if k in held else "dev",
                    _draw(frame, np.random.default_rng([seed, salt, 0, k]))) for k in range(count)]


def select(frame: str, which: str) -> list[Profile]:
    """``dev``, ``heldout``, ``all``, or ``N..M`` (indices, inclusive) or ``N`` of the frame's family."""
    fam = family(frame)
    if which in ("dev", "heldout"):
        return [p for p in fam if p.split == which]
    if which == "all":
        return fam
    m = re.fullmatch(r"(\d+)(?:\.\.(\d+))?", which)
    if not m:
        raise ValueError(f"profiles {which!r}: dev, heldout, all, N or N..M")
    lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
    if not 0 <= lo <= hi < len(fam):
        raise ValueError(f"profiles {which!r}: indices in 0..{len(fam) - 1}")
    return fam[lo:hi + 1]
