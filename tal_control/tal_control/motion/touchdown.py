"""Late and lost touchdowns: a foot the gait plans in stance is a support only while it touches the ground.

The sWBC's stance condition is rigid (J qdd + dJ v = 0, no position feedback) and it plans a ground
reaction force on every stance foot. A foot that is planned in stance but hovers (it reached its swing
target a few millimetres above the ground, or bounced off it) is then driven by torques computed for a
force the ground never gives: on the ViTAL stairs such a foot flew 0.4 m forward within 0.15 s and the
trunk dropped 10 cm (measured, rigid ground, hind and front legs on the landing). ``TouchdownSearch``
keeps such a leg out of the support set and lowers its foot along the surface normal (world z) at
``search_speed_mps`` below the point where it should have touched down, by at most ``max_depth_m``, until
a contact is reported; then the leg becomes a support, anchored where it touched.

Contact flags come from outside: the simulator's contacts in the offline closed loop, the state
estimator's ``contact_estimate`` in the graph. World frame, [m], [s]; legs LF, RF, LH, RH.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tal_control.errors import MotionConfigError
from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS


@dataclass(frozen=True)
class SupportTargets:
    """The legs the WBC may load this tick and the foot references of those it may not.

    supported (4,): planned stance and touching. searching (4,): planned stance, not touching (their
    foot_position/velocity/acceleration rows are the descent; the other rows are the motion's).
    anchored (4,): legs that touched after a search this tick (their stance anchor moved to the foot).
    """

    supported: np.ndarray
    searching: np.ndarray
    anchored: np.ndarray
    foot_position: np.ndarray
    foot_velocity: np.ndarray
    foot_acceleration: np.ndarray


class TouchdownSearch:
    """Per-leg state machine (see the module docstring). One ``update`` per control tick."""

    def __init__(self, search_speed_mps: float = 0.2, max_depth_m: float = 0.08) -> None:
        for name, value in (("search_speed_mps", search_speed_mps), ("max_depth_m", max_depth_m)):
            if not (math.isfinite(value) and value > 0.0):
                raise MotionConfigError(f"TouchdownSearch: {name} must be > 0, got {value!r}")
        self.search_speed_mps = float(search_speed_mps)
        self.max_depth_m = float(max_depth_m)
        self._start = np.full((NUM_LEGS, 3), np.nan)  # [m] where each search began (nan: not searching)
        self._started_s = np.zeros(NUM_LEGS)           # [s]
        self.searches = np.zeros(NUM_LEGS, dtype=np.int64)  # searches started, per leg (diagnostics)

    def update(self, t_s: float, stance: np.ndarray, contact: np.ndarray, foot_position: np.ndarray,
               foot_velocity: np.ndarray, foot_acceleration: np.ndarray,
               measured_foot_position: np.ndarray) -> SupportTargets:
        """stance (4,): planned stance; contact (4,): touching now; foot_* (4, 3): the motion's foot
        references; measured_foot_position (4, 3) [m]. Returns the supports and the references to use."""
        stance = np.asarray(stance, dtype=bool)
        contact = np.asarray(contact, dtype=bool)
        measured = np.asarray(measured_foot_position, dtype=float)
        if stance.shape != (NUM_LEGS,) or contact.shape != (NUM_LEGS,) or measured.shape != (NUM_LEGS, 3):
            raise InputError(f"TouchdownSearch.update: need (4,) stance and contact and (4, 3) foot positions, "
                             f"got {stance.shape}, {contact.shape}, {measured.shape}")
        if not (math.isfinite(t_s) and np.isfinite(measured).all()):
            raise InputError("TouchdownSearch.update: time and foot positions must be finite")
        position = np.array(foot_position, dtype=float)
        velocity = np.array(foot_velocity, dtype=float)
        acceleration = np.array(foot_acceleration, dtype=float)
        searching = stance & ~contact
        was_searching = np.isfinite(self._start[:, 0])
        anchored = stance & contact & was_searching
        self._start[~searching] = np.nan
        for leg in np.flatnonzero(searching):
            if not was_searching[leg]:
                self._start[leg] = measured[leg]
                self._started_s[leg] = t_s
                self.searches[leg] += 1
            depth = self.search_speed_mps * max(t_s - self._started_s[leg], 0.0)
            descending = depth < self.max_depth_m
            position[leg] = self._start[leg] - np.array([0.0, 0.0, min(depth, self.max_depth_m)])
            velocity[leg] = (0.0, 0.0, -self.search_speed_mps if descending else 0.0)
            acceleration[leg] = 0.0
        return SupportTargets(supported=stance & contact, searching=searching, anchored=anchored,
                              foot_position=position, foot_velocity=velocity, foot_acceleration=acceleration)
