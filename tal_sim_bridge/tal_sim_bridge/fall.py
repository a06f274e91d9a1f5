"""Fall detection without ROS: the moment a simulated run stops meaning anything.

``FallDetector`` is fed one sample of the simulation at a time (the bridge does it at the contact rate) and
decides a fall when, for ``confirm_s`` of sim time without a break (a graze does not count), either
  * a robot link other than a foot or a shin touches the ground: the trunk, a hip or an upper leg (thigh),
    the links ``Simulation.body_ground_contact`` reports (shin/ground collisions are filtered there), or
  * the base origin is less than ``min_base_height_m`` above the terrain under it, or there is no terrain
    under it at all (the base left the course).
The fall's time and place are those of the condition's first sample (its onset); its links are every link
that touched the ground while the condition held.

The height bound is a fraction (``DEFAULT_MIN_HEIGHT_RATIO``, as ``tal_lab.closed_loop`` uses) of the robot's
nominal base height: the base origin above flat ground in the nominal pose, which ``Simulation`` computes from
the robot description (0.587 m for HyQ). On ViTAL's stairs (0.1 m rise) the base stays ~0.5 m above the step
under it, on T1 (~6 cm sinkage) ~0.53 m.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from .errors import BridgeConfigError

DEFAULT_MIN_HEIGHT_RATIO = 0.6
"""[-] base origin above the terrain, as a fraction of the nominal base height, below which the robot is down."""
DEFAULT_CONFIRM_S = 0.2
"""[s] how long the condition must hold (a swinging thigh grazing a step nose lasts a few tens of ms)."""


@dataclass(frozen=True)
class Fall:
    """A confirmed fall. Times are sim time [s]; the position is the base origin at the onset [m], world."""

    time_s: float                              # onset: the first sample of the held condition
    confirmed_s: float                         # the sample at which it had held confirm_s
    position_m: tuple[float, float, float]
    links: tuple[str, ...]                     # links on the ground while it held (empty: height only)
    base_height_m: float                       # base origin above the terrain at the onset (NaN: off the course)
    reason: str                                # what held at the onset, in words

    def summary(self) -> dict[str, object]:
        """The summary fields of the bridge's end-of-run JSON."""
        return {"fell": True, "fall_time_s": round(self.time_s, 6), "fall_confirmed_s": round(self.confirmed_s, 6),
                "fall_position_m": [round(v, 4) for v in self.position_m], "fall_links": list(self.links),
                "fall_reason": self.reason}

    def describe(self) -> str:
        x, y, z = self.position_m
        return (f"at t = {self.time_s:.3f} s (confirmed at {self.confirmed_s:.3f} s), base at x {x:.3f}, "
                f"y {y:.3f}, z {z:.3f} m: {self.reason}; links on the ground: {', '.join(self.links) or 'none'}")


NO_FALL_SUMMARY: dict[str, object] = {"fell": False, "fall_time_s": None, "fall_confirmed_s": None,
                                      "fall_position_m": None, "fall_links": [], "fall_reason": None}


class FallDetector:
    """Decides a fall from samples of the simulation state (see the module docstring).

    ``min_base_height_m`` = 0 switches the height criterion off (body contact and leaving the course still
    count); ``confirm_s`` = 0 confirms at the first sample.
    """

    def __init__(self, min_base_height_m: float, confirm_s: float = DEFAULT_CONFIRM_S) -> None:
        if not (math.isfinite(min_base_height_m) and min_base_height_m >= 0.0):
            raise BridgeConfigError(f"fall: min_base_height_m must be finite and >= 0 m, got {min_base_height_m}")
        if not (math.isfinite(confirm_s) and confirm_s >= 0.0):
            raise BridgeConfigError(f"fall: confirm_s must be finite and >= 0 s, got {confirm_s}")
        self.min_base_height_m = float(min_base_height_m)
        self.confirm_s = float(confirm_s)
        self.fall: Fall | None = None
        self._onset: tuple[float, tuple[float, float, float], float, str] | None = None
        self._links: set[str] = set()

    @classmethod
    def for_robot(cls, nominal_base_height_m: float, min_height_ratio: float = DEFAULT_MIN_HEIGHT_RATIO,
                  confirm_s: float = DEFAULT_CONFIRM_S) -> FallDetector:
        """The height bound as ``min_height_ratio`` of the robot's nominal base height [m]."""
        if not (math.isfinite(nominal_base_height_m) and nominal_base_height_m > 0.0):
            raise BridgeConfigError(f"fall: the nominal base height must be > 0 m, got {nominal_base_height_m}")
        if not (math.isfinite(min_height_ratio) and 0.0 <= min_height_ratio <= 1.0):
            raise BridgeConfigError(f"fall: min_height_ratio must be in [0, 1], got {min_height_ratio}")
        return cls(min_height_ratio * nominal_base_height_m, confirm_s)

    def update(self, time_s: float, base_position_m: Sequence[float], terrain_height_m: float,
               body_contacts: Iterable[str]) -> Fall | None:
        """Feed one sample: sim time [s], base origin [m] (world), terrain height under it [m] (NaN: none),
        the links other than feet touching the ground. Returns the fall at the sample that confirms it, None
        otherwise (and for every sample after it: the first fall is the run's)."""
        if self.fall is not None:
            return None
        links = set(body_contacts)
        height = float(base_position_m[2]) - float(terrain_height_m)
        reason = self._reason(links, height)
        if reason is None:
            self._onset = None
            self._links.clear()
            return None
        if self._onset is None:
            position = (float(base_position_m[0]), float(base_position_m[1]), float(base_position_m[2]))
            self._onset = (float(time_s), position, height, reason)
        self._links |= links
        onset_s, position, onset_height, onset_reason = self._onset
        if time_s - onset_s < self.confirm_s - 1e-9:
            return None
        self.fall = Fall(onset_s, float(time_s), position, tuple(sorted(self._links)), onset_height, onset_reason)
        return self.fall

    def _reason(self, links: set[str], height_m: float) -> str | None:
        if links:
            return "body-ground contact"
        if math.isnan(height_m):
            return "no terrain under the base (off the course)"
        if height_m < self.min_base_height_m:
            return f"base {height_m:.3f} m above the terrain, below the bound {self.min_base_height_m:.3f} m"
        return None

    def summary(self) -> dict[str, object]:
        return dict(NO_FALL_SUMMARY) if self.fall is None else self.fall.summary()
