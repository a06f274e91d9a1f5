"""Late and lost touchdowns: a foot the gait plans in stance is a support only while it touches the ground.

The sWBC's stance condition is rigid (J qdd + dJ v = 0, no position feedback) and it plans a ground
reaction force on every stance foot. A foot that is planned in stance but hovers (it reached its swing
target a few millimetres above the ground, or bounced off it) is then driven by torques computed for a
force the ground never gives: on the ViTAL stairs such a foot flew 0.4 m forward within 0.15 s and the
trunk dropped 10 cm (measured, rigid ground, hind and front legs on the landing). ``TouchdownSearch``
keeps such a leg out of the support set and lowers its foot straight down (world z) at ``search_speed_mps``
from where it was when the search began, by at most ``max_depth_m``, until a contact is reported; then
the leg becomes a support, anchored where it touched.

The converse, an early touchdown: a swinging foot that touches the ground after ``early_touchdown_progress``
of its swing (it is coming down onto a step that is higher, or a surface that is nearer, than planned) is a
support from then on, held where it touched, instead of being pushed on through the ground by the swing
task while the WBC plans no force for it. Contacts earlier in the swing (lift-off, tripping on an edge)
stay swing contacts.

Contact flags come from outside: the simulator's contacts, in the offline closed loop and, through the
bridge's ``ground_truth/contacts`` (the ``wbc`` node's ``contact_source``), in the graph; or the feet's
contact sensors (``foot_contacts``), whose flag comes a sample late and only once the load passes a
threshold. ``contact_grace_s``: for that long after a planned touchdown a leg is a support as planned even
without a reported contact (the sensor's latency); only then does its search begin (with one sample of
sensor delay and no grace, every touchdown started a search, the trot lost a diagonal's support and HyQ fell
at 5 s). ``latch_contact``: a contact reported once in a planned stance holds until lift-off (a load sensor's
flag drops when the QP loads a stance foot lightly, down to its 10 N minimum, below a 50 N threshold: such a
foot is touching, not lost); the search is then for feet that never reported their touchdown. World frame,
[m], [s]; legs LF, RF, LH, RH.
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

    supported (4,): touching and either planned stance or landed early. searching (4,): planned stance,
    not touching (their foot_position/velocity/acceleration rows are the descent; the other rows are the
    motion's). anchored (4,): legs that touched after a search this tick (their stance anchor moved to the
    foot). early (4,): swinging legs that landed early (supports held where they touched).
    """

    supported: np.ndarray
    searching: np.ndarray
    anchored: np.ndarray
    early: np.ndarray
    foot_position: np.ndarray
    foot_velocity: np.ndarray
    foot_acceleration: np.ndarray


class TouchdownSearch:
    """Per-leg state machine (see the module docstring). One ``update`` per control tick."""

    def __init__(self, search_speed_mps: float = 0.2, max_depth_m: float = 0.08,
                 early_touchdown_progress: float = 0.7, contact_grace_s: float = 0.0,
                 latch_contact: bool = False) -> None:
        for name, value in (("search_speed_mps", search_speed_mps), ("max_depth_m", max_depth_m)):
            if not (math.isfinite(value) and value > 0.0):
                raise MotionConfigError(f"TouchdownSearch: {name} must be > 0, got {value!r}")
        if not (math.isfinite(contact_grace_s) and contact_grace_s >= 0.0):
            raise MotionConfigError(f"TouchdownSearch: contact_grace_s must be >= 0, got {contact_grace_s!r}")
        self.contact_grace_s = float(contact_grace_s)
        self.latch_contact = bool(latch_contact)
        self._confirmed = np.zeros(NUM_LEGS, dtype=bool)    # contact reported in the current planned stance
        self._stance_since = np.full(NUM_LEGS, -math.inf)  # [s] start of each leg's planned stance
        self._was_stance = np.zeros(NUM_LEGS, dtype=bool)
        if not (math.isfinite(early_touchdown_progress) and 0.0 < early_touchdown_progress <= 1.0):
            raise MotionConfigError(f"TouchdownSearch: early_touchdown_progress must be in (0, 1], "
                                    f"got {early_touchdown_progress!r}")
        self.search_speed_mps = float(search_speed_mps)
        self.max_depth_m = float(max_depth_m)
        self.early_touchdown_progress = float(early_touchdown_progress)
        self._landed = np.full((NUM_LEGS, 3), np.nan)  # [m] where an early touchdown held the foot
        self._start = np.full((NUM_LEGS, 3), np.nan)  # [m] where each search began (nan: not searching)
        self._started_s = np.zeros(NUM_LEGS)           # [s]
        self.searches = np.zeros(NUM_LEGS, dtype=np.int64)  # searches started, per leg (diagnostics)
        self.early_touchdowns = np.zeros(NUM_LEGS, dtype=np.int64)  # per leg (diagnostics)

    def update(self, t_s: float, stance: np.ndarray, contact: np.ndarray, foot_position: np.ndarray,
               foot_velocity: np.ndarray, foot_acceleration: np.ndarray,
               measured_foot_position: np.ndarray, swing_progress: np.ndarray | None = None) -> SupportTargets:
        """stance (4,): planned stance; contact (4,): touching now; foot_* (4, 3): the motion's foot
        references; measured_foot_position (4, 3) [m]; swing_progress (4,) [0, 1] of the swinging legs
        (None: no early touchdowns). Returns the supports and the references to use."""
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
        began = stance & ~self._was_stance
        self._stance_since[began] = t_s
        self._was_stance = stance.copy()
        if self.latch_contact:
            self._confirmed = stance & (self._confirmed & ~began | contact)
            contact = contact | self._confirmed
        if self.contact_grace_s > 0.0:   # a reported contact may be late: trust the plan that long
            contact = contact | (stance & (t_s - self._stance_since < self.contact_grace_s - 1e-9))
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
        early = np.zeros(NUM_LEGS, dtype=bool)
        if swing_progress is not None:
            progress = np.asarray(swing_progress, dtype=float).reshape(-1)
            if progress.shape != (NUM_LEGS,):
                raise InputError(f"TouchdownSearch.update: swing_progress must have 4 entries, got {progress.shape}")
            held = np.isfinite(self._landed[:, 0])
            # Once landed early, a leg stays a support while it touches, until its planned stance begins.
            early = ~stance & contact & (held | (progress >= self.early_touchdown_progress))
            for leg in np.flatnonzero(early & ~held):
                self._landed[leg] = measured[leg]
                self.early_touchdowns[leg] += 1
            position[early] = self._landed[early]
            velocity[early] = 0.0
            acceleration[early] = 0.0
        self._landed[~early] = np.nan
        return SupportTargets(supported=(stance & contact) | early, searching=searching, anchored=anchored,
                              early=early, foot_position=position, foot_velocity=velocity,
                              foot_acceleration=acceleration)
