"""VFA planner: when to select a foothold for which leg, from the gait state and the latest heightmap.

The ``vfa`` node is a thin adapter over this module (no rclpy here). Per swinging leg the planner
decides once per swing (the swing's ``step_count``) and re-decides during the swing, while at least
``min_swing_time_left_s`` of it is left, when

* a newer heightmap arrived (``reevaluate_on_new_map``; the thesis' VFA adapts the footholds
  continuously as the map is updated), or
* the nominal foothold moved horizontally by more than ``nominal_shift_threshold_m`` since the last
  decision (the motion generator keeps re-planning its Raibert foothold as the velocity changes; once it
  was given an external foothold it stops following the nominal itself, so the VFA must).

Late re-decisions stay on the same level: the swing re-plans its rise to the apex only until shortly
before mid-swing (``tal_control.motion.swing``); a later retarget goes from wherever the foot is
straight to the new point, which is not the lift-off -> apex -> candidate motion the FEC checked. Past
``level_lock_swing_fraction`` of the swing a re-decision whose foothold height differs by more than
``level_lock_dz_m`` from the current one is not taken (counted in ``level_locked``): on the stairs at
0.4 m/s a selection that moved down a tread and back up after the apex drove the foot into the riser.
Same-level moves stay allowed: they carry the nominal's velocity feedback (locking every late
re-decision made the 0.2 m/s stairs runs fall sideways).

A re-decision keeps the swing's current selection, instead of jumping more than ``switch_hysteresis_m``
from it, while that point is still safe and no more than ``switch_hysteresis_m`` further from the new
nominal than the new best candidate: near a step edge two
safe regions can be almost equally close to the nominal, and flipping between them mid-swing retargets
the foot by a whole tread (a jolt for the whole-body controller) for no gain in safety.

Diagonal-pair compensation (``pair_compensation_m`` > 0; ours, not the thesis'): in a trot the two legs
of a diagonal land together and their support line must pass under the CoM, or the trunk tips about it
for the whole two-leg phase (no contact force on that line has a moment about it). When the VFA moves
one leg of a swinging pair away from its nominal (a stair edge), the partner's nominal is shifted by
the opposite amount (at most ``pair_compensation_m``) and the partner re-decided around it, so the
line's midpoint stays where the nominals put it. The leg that moved more leads; the compensated
decision keeps the gait's nominal in ``nominal`` (trigger "pair"). On ViTAL's stairs at 0.2 m/s a front
foot moved 6-8 cm back from a tread edge left the CoM 4-8 cm ahead of the line; the trunk pitched 10 deg
past its reference and the front shin hit the edge above.

Batching: the legs that need a decision at the same tick (a trot's diagonal pair usually starts its
swing, or sees a new map, together) are selected in one ``select_legs`` call when the selector has one
(the CNN's: one network pass instead of one per leg); each leg's trigger, hysteresis and level lock read
only that leg's state, so the decisions are those of one ``select`` per leg (tested). The exact selector
is called one leg at a time.

A re-decision is reported only when it changes something (the selection by more than
``selection_tolerance_m``, or the status), so the consumer re-targets the swing only when needed.

Inputs: ``GaitSnapshot`` (the ``tal_msgs/GaitState`` as arrays, world frame) and a ``HeightMapGrid`` with
its stamp. Derived per leg: the heading of the horizontal frame (from the hip positions, so no base
pose is needed), the hip height (world z of the HAA joint, from the gait state; with
``predict_hip_descent`` the lower of now and at touchdown, from the gait state's hip velocity), the hip at touchdown
(current hip moved by the commanded hip velocity over the time to touchdown) and the lift-off foothold
(the lift-off foot centre minus the foot radius). Now is the gait state's stamp (sim time): the map's
age is measured against the control tick the decision is for.

A missing or stale map (``|gait stamp - map stamp| > max_map_age_s``) passes the nominal through
flagged (``VfaStatus.NO_MAP`` / ``STALE_MAP``), so does a patch without any safe candidate
(``NO_SAFE_CANDIDATE``); neither raises. A malformed gait state or map raises ``VfaInputError`` with a
reason the node counts.

Selectors: anything with ``FootholdSelector.select``'s signature (``SelectorLike``); ``make_selector``
builds one by name ("exact" now; the CNN approximation is wired there).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_core.heightmap import HeightMapGrid
from tal_core.legs import LEGS, NUM_LEGS, Leg
from tal_core.robot_model import RobotModel
from tal_perception.errors import FecConfigError, VfaInputError
from tal_perception.fec import FootholdEvaluator
from tal_perception.fec_settings import FecSettings, GaitTiming
from tal_perception.vfa import FootholdRequest, FootholdSelector, VfaStatus

FloatArray = NDArray[np.float64]
SELECTORS: tuple[str, ...] = ("exact", "cnn", "cnn_unverified")
CLOCK_RESET_S = 0.5  # [s] a stamp this far behind the last one is a restarted clock, not reordering
DIAGONAL_PAIRS: tuple[tuple[Leg, Leg], ...] = ((Leg.LF, Leg.RH), (Leg.RF, Leg.LH))


class SelectorLike(Protocol):
    """What the planner needs from a foothold selector (``tal_perception.vfa.FootholdSelector``'s
    interface). Its result has ``selected``, ``any_safe``, ``status``, ``safe_candidates`` and, when it
    is an approximation, ``score`` [-] (a result without it is an exact evaluation: score 1)."""

    def select(self, leg: Leg, nominal_world: ArrayLike, grid: HeightMapGrid | None, *, hip_height_m: float,
               twist: ArrayLike, gait: GaitTiming, yaw: float | None = None, map_age_s: float = 0.0,
               liftoff_world: ArrayLike | None = None,
               hip_touchdown_world: ArrayLike | None = None) -> Any: ...


def make_selector(name: str, model: RobotModel, *, max_map_age_s: float,
                  fec_settings: FecSettings | None = None) -> SelectorLike:
    """The foothold selector called ``name`` for ``model``: "exact" is the lazy exact FEC evaluation
    (``FootholdSelector``), "cnn" the thesis' CNN approximation with the committed weights, its choice
    verified by the exact criteria on that one candidate (exact search when it fails: the CNN alone picks
    an unsafe foothold in 12.2 % of the accuracy protocol's tuples, ``results/vital/vfa_cnn_accuracy.md``),
    "cnn_unverified" the CNN's choice as it is (the thesis' g_hat; for comparisons)."""
    if name == "exact":
        return FootholdSelector(FootholdEvaluator(model, fec_settings), max_map_age_s=max_map_age_s)
    if name in ("cnn", "cnn_unverified"):
        from tal_perception.vfa_cnn import CnnFootholdSelector  # torch: imported only when asked for

        return CnnFootholdSelector(FootholdEvaluator(model, fec_settings), max_map_age_s=max_map_age_s,
                                   verify=name == "cnn")
    raise FecConfigError(f"selector must be one of {list(SELECTORS)}, got {name!r}")


@dataclass(frozen=True)
class PlannerSettings:
    """When the planner (re-)decides; SI units, see the module docstring."""

    max_map_age_s: float = 0.5  # [s] a map further than this from the gait state's stamp is stale
    min_swing_time_left_s: float = 0.08  # [s] no (re-)decision later in a swing (the wbc needs 0.05 s)
    nominal_shift_threshold_m: float = 0.02  # [m] re-decide when the nominal moved this far (one cell)
    reevaluate_on_new_map: bool = True  # re-decide when a newer map arrives during the swing
    selection_tolerance_m: float = 1e-3  # [m] a re-decision closer than this to the last is not news
    switch_hysteresis_m: float = 0.05  # [m] keep a still-safe selection unless the new one is this much closer
    level_lock_swing_fraction: float = 0.35  # [-] after this fraction of the swing, no change of level...
    level_lock_dz_m: float = 0.02  # [m] ...by more than this (foothold height)
    pair_compensation_m: float = 0.0  # [m] largest shift of a diagonal partner's nominal (0: off)
    pair_min_adaptation_m: float = 0.02  # [m] smaller adaptations of the leading leg are not compensated
    # Evaluate at the hip's predicted height at touchdown when it is lower than now (see _fec_hip_height).
    predict_hip_descent: bool = False

    def __post_init__(self) -> None:
        for name in ("max_map_age_s", "min_swing_time_left_s", "nominal_shift_threshold_m", "selection_tolerance_m",
                     "switch_hysteresis_m", "pair_compensation_m", "pair_min_adaptation_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise FecConfigError(f"PlannerSettings.{name} must be a finite number, got {value!r}")
            if value < 0.0 or (name == "max_map_age_s" and value == 0.0):
                raise FecConfigError(f"PlannerSettings.{name} must be {'> 0' if name == 'max_map_age_s' else '>= 0'}"
                                     f", got {value!r}")
        fraction = self.level_lock_swing_fraction
        if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0.0 <= fraction <= 1.0:
            raise FecConfigError(f"PlannerSettings.level_lock_swing_fraction must be in [0, 1], got {fraction!r}")
        lock = self.level_lock_dz_m
        if isinstance(lock, bool) or not isinstance(lock, (int, float)) or not (math.isfinite(lock) and lock >= 0.0):
            raise FecConfigError(f"PlannerSettings.level_lock_dz_m must be a finite number >= 0, got {lock!r}")
        for name in ("reevaluate_on_new_map", "predict_hip_descent"):
            if not isinstance(getattr(self, name), bool):
                raise FecConfigError(f"PlannerSettings.{name} must be a bool, got {getattr(self, name)!r}")


@dataclass(frozen=True, eq=False)
class GaitSnapshot:
    """The gait state of one control tick (``tal_msgs/GaitState``), world frame, legs LF, RF, LH, RH.

    stamp_s [s] the control tick; step_frequency_hz [Hz]; duty_factor [-]; step_height_m [m];
    base_twist (6,) [m/s, rad/s] commanded, horizontal frame; swing (4,) bool; time_to_touchdown_s (4,)
    [s]; step_count (4,) [-]; liftoff_position (4, 3) [m] foot centres at the last lift-off;
    nominal_foothold (4, 3) [m] terrain points; hip_position (4, 3) [m] HAA joints; hip_velocity (4, 3)
    [m/s] the HAA joints' velocities in the trunk reference (None: zeros, e.g. from an older gait_state).
    """

    stamp_s: float
    step_frequency_hz: float
    duty_factor: float
    step_height_m: float
    base_twist: FloatArray
    swing: NDArray[np.bool_]
    time_to_touchdown_s: FloatArray
    step_count: NDArray[np.int64]
    liftoff_position: FloatArray
    nominal_foothold: FloatArray
    hip_position: FloatArray
    hip_velocity: FloatArray | None = None

    def __post_init__(self) -> None:
        if self.hip_velocity is None:
            object.__setattr__(self, "hip_velocity", np.zeros((NUM_LEGS, 3)))
        shapes = {"base_twist": (6,), "time_to_touchdown_s": (NUM_LEGS,), "liftoff_position": (NUM_LEGS, 3),
                  "nominal_foothold": (NUM_LEGS, 3), "hip_position": (NUM_LEGS, 3), "hip_velocity": (NUM_LEGS, 3)}
        for name, shape in shapes.items():
            object.__setattr__(self, name, _finite_array(getattr(self, name), shape, name))
        for name in ("stamp_s", "step_frequency_hz", "duty_factor", "step_height_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not math.isfinite(value):
                raise VfaInputError("gait_state_nan", f"gait state: {name} must be a finite number, got {value!r}")
        swing = np.asarray(self.swing)
        counts = np.asarray(self.step_count)
        for name, array in (("swing", swing), ("step_count", counts)):
            if array.shape != (NUM_LEGS,):
                raise VfaInputError("gait_state_size", f"gait state: {name} must have {NUM_LEGS} values "
                                    f"(LF, RF, LH, RH), got shape {array.shape}")
        if swing.dtype != np.bool_:
            raise VfaInputError("gait_state_invalid", f"gait state: swing must be booleans, got {swing.dtype}")
        if not np.issubdtype(counts.dtype, np.integer) or (counts < 0).any():
            raise VfaInputError("gait_state_invalid", f"gait state: step_count must be integers >= 0, got {counts}")
        object.__setattr__(self, "swing", swing.copy())
        object.__setattr__(self, "step_count", counts.astype(np.int64))
        if swing.any():
            if self.step_frequency_hz <= 0.0 or not 0.0 < self.duty_factor < 1.0 or self.step_height_m < 0.0:
                raise VfaInputError("gait_state_invalid", "gait state: a leg swings, so step_frequency_hz must be "
                                    f"> 0 (got {self.step_frequency_hz}), duty_factor in (0, 1) (got "
                                    f"{self.duty_factor}) and step_height_m >= 0 (got {self.step_height_m})")
            negative = [leg.name for leg in LEGS if swing[leg] and self.time_to_touchdown_s[leg] < 0.0]
            if negative:
                raise VfaInputError("gait_state_invalid", f"gait state: time_to_touchdown_s < 0 for swinging "
                                    f"leg(s) {', '.join(negative)}")


@dataclass(frozen=True, eq=False)
class FootholdDecision:
    """The foothold for one swing of one leg. Positions (3,) [m] world frame, terrain points.

    safe_candidates: the number of safe candidates when the selector knows it (None: lazy search or not
    evaluated); score [-]: the selector's confidence (1 for the exact evaluation, 0 when nothing was
    evaluated: no map or a stale one); trigger: why it was decided ("swing_start", "new_map",
    "nominal_moved"); elapsed_s [s] wall time of the selection (in a batched selection of several legs: the
    call's time / its legs, plus this leg's hysteresis check).
    """

    leg: Leg
    step_count: int
    nominal: FloatArray
    selected: FloatArray
    safe_candidate_found: bool
    safe_candidates: int | None
    score: float
    status: VfaStatus
    trigger: str
    map_stamp_s: float | None
    elapsed_s: float

    @property
    def adapted(self) -> bool:
        """True if the selection differs from the nominal foothold (by more than 1 um)."""
        return bool(np.linalg.norm(self.selected - self.nominal) > 1e-6)


@dataclass
class PlannerCounters:
    """Counts since start: decisions by status and trigger, swings first seen too late to decide."""

    by_status: dict[str, int] = field(default_factory=lambda: {s.value: 0 for s in VfaStatus})
    by_trigger: dict[str, int] = field(default_factory=lambda: {"swing_start": 0, "new_map": 0, "nominal_moved": 0,
                                                                "pair": 0})
    adapted: int = 0
    late_swings: int = 0
    restarts: int = 0
    kept: int = 0  # re-decisions that kept the swing's still-safe selection (switch hysteresis)
    level_locked: int = 0  # late re-decisions not taken because they changed the foothold's level


class HipFrame:
    """The base pose as seen from a gait state's hips (HAA joints, world frame), with the base level:
    heading from the front hips seen from the hind hips, base origin from the hips' centre.

    hip_offsets_base (4, 3) [m]: the HAA joints in the base frame.
    """

    def __init__(self, hip_offsets_base: ArrayLike) -> None:
        hips = np.asarray(hip_offsets_base, dtype=float)
        if hips.shape != (NUM_LEGS, 3) or not np.isfinite(hips).all():
            raise FecConfigError(f"hip_offsets_base must be (4, 3) finite values [m], got shape {hips.shape}")
        front_to_hind = _front_minus_hind(hips[:, :2])
        if np.linalg.norm(front_to_hind) < 1e-3:
            raise FecConfigError("hip_offsets_base: the front and hind hips coincide, no heading can be derived")
        self.offsets_base = hips
        self._heading_base = math.atan2(front_to_hind[1], front_to_hind[0])
        self._centre_base = hips.mean(axis=0)

    @classmethod
    def from_model(cls, model: RobotModel) -> HipFrame:
        """The hips of ``model`` in its neutral standing pose."""
        neutral = RobotModel(model.description)  # private copy: updating it must not disturb the caller's
        height = neutral.nominal_base_height_m
        neutral.update(neutral.neutral_q(height), np.zeros(neutral.nv))
        return cls(neutral.hip_positions() - np.array([0.0, 0.0, height]))

    def heading(self, hip_world: FloatArray) -> float:
        """[rad] world yaw of the base: direction of the front hips seen from the hind hips, minus the same
        direction in the base frame (exact for any roll and pitch: it is the base x axis' projection)."""
        d = _front_minus_hind(hip_world[:, :2])
        return math.remainder(math.atan2(d[1], d[0]) - self._heading_base, 2.0 * math.pi)

    def base_position(self, hip_world: FloatArray, yaw: float) -> FloatArray:
        """(3,) [m] world base origin from the hips (4, 3) [m] world, the base taken level at ``yaw``."""
        c, s = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return hip_world.mean(axis=0) - rotation @ self._centre_base


class VfaPlanner:
    """Per-leg foothold decisions for the swinging legs (see the module docstring).

    hip_offsets_base (4, 3) [m]: the HAA joints in the base frame (they give the heading and the base's
    rotation centre); foot_radius_m [m]: lift-off foot centre -> terrain point.
    """

    def __init__(self, selector: SelectorLike, hip_offsets_base: ArrayLike, foot_radius_m: float,
                 settings: PlannerSettings | None = None) -> None:
        self.selector = selector
        self.settings = settings if settings is not None else PlannerSettings()
        self.hips = HipFrame(hip_offsets_base)
        if not (math.isfinite(foot_radius_m) and foot_radius_m >= 0.0):
            raise FecConfigError(f"foot_radius_m must be a finite value >= 0 [m], got {foot_radius_m!r}")
        self.foot_radius_m = float(foot_radius_m)
        self.counters = PlannerCounters()
        self.reset()

    @classmethod
    def for_robot(cls, model: RobotModel, selector: str = "exact", settings: PlannerSettings | None = None,
                  fec_settings: FecSettings | None = None) -> VfaPlanner:
        """A planner for ``model`` with the selector called ``selector`` (``make_selector``)."""
        settings = settings if settings is not None else PlannerSettings()
        chosen = make_selector(selector, model, max_map_age_s=settings.max_map_age_s, fec_settings=fec_settings)
        hips = HipFrame.from_model(model).offsets_base
        return cls(chosen, hips, float(model.description.foot_radius_m), settings)

    def warm_up(self) -> float:
        """One selection per leg on a flat synthetic map under the standing robot, not counted (and, for a
        selector with ``select_legs``, one call of 2, 3 and 4 legs): builds the selector's caches so that the
        first real swing does not pay for them. Returns its wall time [s]."""
        start = time.perf_counter()
        height = 0.5  # [m] a plausible hip height above the flat map (the result is not used)
        grid = HeightMapGrid(center_xy=(0.0, 0.0), yaw=0.0, resolution_m=0.02, heights=np.zeros((81, 81)))
        timing = GaitTiming(step_frequency_hz=1.5, duty_factor=0.6, swing_time_left_s=0.2, step_height_m=0.1)
        for leg in LEGS:
            self.selector.select(leg, np.zeros(3), grid, hip_height_m=height, twist=np.zeros(6), gait=timing)
        select_legs = getattr(self.selector, "select_legs", None)
        if select_legs is not None:  # the batched calls of 2-4 legs have their own buffers (CNN selector)
            requests = [FootholdRequest(leg, np.zeros(3), height, np.zeros(6), timing) for leg in LEGS]
            for count in range(2, len(LEGS) + 1):
                select_legs(requests[:count], grid)
        return time.perf_counter() - start

    def reset(self) -> None:
        """Forget the map, the last stamps and every decision (a restarted clock)."""
        self._grid: HeightMapGrid | None = None
        self._map_stamp_s: float | None = None
        self._gait_stamp_s: float | None = None
        self._decisions: dict[Leg, FootholdDecision] = {}
        self._late_step: dict[Leg, int] = {}  # the swing of each leg first seen with too little time left
        self._compensation: dict[Leg, FloatArray] = {}  # (2,) [m] shift of the nominal in a leg's decision

    @property
    def map_stamp_s(self) -> float | None:
        """[s] stamp of the map in use (None: no map yet)."""
        return self._map_stamp_s

    def decision(self, leg: Leg) -> FootholdDecision | None:
        """The current decision for ``leg``'s swing (None in stance or before the first decision)."""
        return self._decisions.get(Leg(leg))

    # -- inputs -------------------------------------------------------------------------------------
    def set_map(self, grid: HeightMapGrid, stamp_s: float) -> bool:
        """Use ``grid`` (world heights [m], NaN unknown) sampled at ``stamp_s`` [s] from now on. Returns
        False (and keeps the map in use) for a repeated map: the same stamp as the one in use (the
        simulator repeats its first sample until the controller answers).

        Raises VfaInputError: stamp before the previous map's (``heightmap_out_of_order``; a jump back
        of more than ``CLOCK_RESET_S`` restarts the planner instead), heights of +-inf
        (``heightmap_invalid``)."""
        if not isinstance(grid, HeightMapGrid):
            raise VfaInputError("heightmap_invalid", f"heightmap must be a HeightMapGrid, got {type(grid).__name__}")
        if not math.isfinite(stamp_s):
            raise VfaInputError("heightmap_invalid", f"heightmap stamp must be finite [s], got {stamp_s!r}")
        if np.isinf(grid.heights).any():
            raise VfaInputError("heightmap_invalid", f"heightmap has {int(np.isinf(grid.heights).sum())} infinite "
                                "height(s) (unknown cells must be NaN)")
        last = self._map_stamp_s
        if last is not None and stamp_s == last:
            return False
        if last is not None and stamp_s < last:
            if stamp_s + CLOCK_RESET_S < last:
                self._restart()
            else:
                raise VfaInputError("heightmap_out_of_order", f"heightmap stamp {stamp_s:.6f} s is before the "
                                    f"previous map's {last:.6f} s")
        self._grid, self._map_stamp_s = grid, float(stamp_s)
        return True

    def update(self, gait: GaitSnapshot) -> list[FootholdDecision]:
        """New or changed decisions for the swinging legs at the gait state's tick (empty: no news).

        Raises VfaInputError when the gait state is not a GaitSnapshot or its stamp is not after the
        previous one (``gait_state_out_of_order``; a jump back of more than ``CLOCK_RESET_S``
        restarts the planner instead)."""
        if not isinstance(gait, GaitSnapshot):
            raise VfaInputError("gait_state_invalid", f"gait state must be a GaitSnapshot, got {type(gait).__name__}")
        last = self._gait_stamp_s
        if last is not None and gait.stamp_s <= last:
            if gait.stamp_s + CLOCK_RESET_S < last:
                self._restart()
            else:
                raise VfaInputError("gait_state_out_of_order", f"gait state stamp {gait.stamp_s:.6f} s is not "
                                    f"after the previous one's {last:.6f} s")
        self._gait_stamp_s = gait.stamp_s
        news: list[FootholdDecision] = []
        pending: list[tuple[Leg, str]] = []  # the legs that need a decision this tick, in LEGS order
        for leg in LEGS:
            if not gait.swing[leg]:
                self._decisions.pop(leg, None)
                continue
            trigger = self._trigger(leg, gait)
            if trigger is not None:
                pending.append((leg, trigger))
        # Each leg's trigger and decision read only that leg's state, so deciding all of them first (one
        # batched selection) and then committing them in LEGS order is the same as one leg at a time.
        for (leg, _trigger), decision in zip(pending, self._decide_legs(gait, pending)):
            previous = self._decisions.get(leg)
            if previous is not None and self._changes_level_late(leg, gait, previous, decision):
                # Keep the selection, but as seen with this map and nominal (no re-trigger next tick).
                self.counters.level_locked += 1
                self._decisions[leg] = replace(previous, nominal=decision.nominal, map_stamp_s=decision.map_stamp_s)
                continue
            self._decisions[leg] = decision
            self._count(decision)
            if previous is None or self._differs(previous, decision):
                news.append(decision)
        if self.settings.pair_compensation_m > 0.0:
            news = self._compensate_pairs(gait, news)
        return news

    def _compensate_pairs(self, gait: GaitSnapshot, news: list[FootholdDecision]) -> list[FootholdDecision]:
        """Re-decide the partner of a swinging diagonal pair around its nominal shifted by minus the other
        leg's own adaptation (module docstring); returns ``news`` with those decisions replaced."""
        s = self.settings
        for decision in news:  # decided from the leg's own nominal this tick
            self._compensation.pop(decision.leg, None)
        for leg in [leg for leg in self._compensation if leg not in self._decisions]:
            del self._compensation[leg]
        for first, second in DIAGONAL_PAIRS:
            if first not in self._decisions or second not in self._decisions:
                continue
            own = {leg: self._own_adaptation(leg) for leg in (first, second)}
            leader = first if np.linalg.norm(own[first]) >= np.linalg.norm(own[second]) else second
            follower = second if leader is first else first
            shift = -own[leader] if np.linalg.norm(own[leader]) > s.pair_min_adaptation_m else np.zeros(2)
            size = float(np.linalg.norm(shift))
            if size > s.pair_compensation_m:
                shift *= s.pair_compensation_m / size
            current = self._compensation.get(follower, np.zeros(2))
            if (np.linalg.norm(shift - current) <= 0.5 * s.nominal_shift_threshold_m
                    or gait.time_to_touchdown_s[follower] < s.min_swing_time_left_s):
                continue
            nominal = gait.nominal_foothold.copy()
            nominal[follower, :2] += shift
            previous = self._decisions[follower]
            decision = self._decide(follower, replace(gait, nominal_foothold=nominal), "pair")
            decision = replace(decision, nominal=gait.nominal_foothold[follower].copy())
            if self._changes_level_late(follower, gait, previous, decision):
                continue
            self._decisions[follower] = decision
            self._compensation[follower] = shift
            self._count(decision)
            news = [d for d in news if d.leg is not follower] + [decision]
        return news

    def _own_adaptation(self, leg: Leg) -> FloatArray:
        """(2,) [m] how far the VFA moved ``leg``'s selection from its (compensated) nominal, horizontally."""
        decision = self._decisions[leg]
        return decision.selected[:2] - decision.nominal[:2] - self._compensation.get(leg, np.zeros(2))

    # -- decisions ----------------------------------------------------------------------------------
    def _trigger(self, leg: Leg, gait: GaitSnapshot) -> str | None:
        """Why ``leg`` needs a (new) decision now, or None."""
        s = self.settings
        step = int(gait.step_count[leg])
        previous = self._decisions.get(leg)
        if previous is not None and previous.step_count != step:
            previous = None  # a new swing began without a stance tick in between (e.g. a skipped tick)
        if gait.time_to_touchdown_s[leg] < s.min_swing_time_left_s:
            if previous is None and self._late_step.get(leg) != step:
                self._late_step[leg] = step
                self.counters.late_swings += 1
            return None
        if previous is None:
            return "swing_start"
        if s.reevaluate_on_new_map and self._map_stamp_s is not None and previous.map_stamp_s != self._map_stamp_s:
            return "new_map"
        if np.linalg.norm(gait.nominal_foothold[leg, :2] - previous.nominal[:2]) > s.nominal_shift_threshold_m:
            return "nominal_moved"
        return None

    def _decide(self, leg: Leg, gait: GaitSnapshot, trigger: str) -> FootholdDecision:
        """The decision for ``leg`` at this tick (one selection, then the switch hysteresis)."""
        return self._decide_legs(gait, [(leg, trigger)])[0]

    def _decide_legs(self, gait: GaitSnapshot, pending: list[tuple[Leg, str]]) -> list[FootholdDecision]:
        """The decisions for the (leg, trigger) pairs of ``pending`` at this tick, in its order.

        Two or more legs with a selector that has ``select_legs`` (the CNN's): one batched selection (one
        network pass; a trot's diagonal pair usually swings and is decided together), each decision's
        ``elapsed_s`` its share of the call (call time / legs) plus its own hysteresis check. Otherwise
        one ``select`` per leg. The selections are the same either way (each leg's result depends only on
        its own request and the map; tested)."""
        if not pending:
            return []
        yaw = self.hips.heading(gait.hip_position)
        map_age = math.inf if self._map_stamp_s is None else abs(gait.stamp_s - self._map_stamp_s)
        map_age_s = 0.0 if self._grid is None else map_age  # the selector's argument (no map: not read)
        requests = [self._request(leg, gait, yaw) for leg, _ in pending]
        select_legs = getattr(self.selector, "select_legs", None)
        if len(requests) > 1 and select_legs is not None:
            start = time.perf_counter()
            results = select_legs(requests, self._grid, yaw=yaw, map_age_s=map_age_s)
            shares = [(time.perf_counter() - start) / len(requests)] * len(requests)
        else:
            results, shares = [], []
            for request in requests:
                start = time.perf_counter()
                results.append(self._select(request, yaw, map_age_s))
                shares.append(time.perf_counter() - start)
        return [self._conclude(gait, trigger, request, result, yaw, map_age_s, share)
                for (_, trigger), request, result, share in zip(pending, requests, results, shares)]

    def _request(self, leg: Leg, gait: GaitSnapshot, yaw: float) -> FootholdRequest:
        """``leg``'s selector inputs at this tick: its nominal, hip height, the twist, the gait timing with
        the time left [s], its lift-off foothold and its hip at touchdown (world frame, heading ``yaw`` [rad])."""
        timing = GaitTiming(
            step_frequency_hz=float(gait.step_frequency_hz), duty_factor=float(gait.duty_factor),
            swing_time_left_s=0.0, step_height_m=float(gait.step_height_m))
        # The scheduler's time to touchdown may exceed (1 - D) / f by rounding or during a gait switch.
        time_left = float(np.clip(gait.time_to_touchdown_s[leg], 0.0, timing.swing_duration_s))
        timing = GaitTiming(timing.step_frequency_hz, timing.duty_factor, time_left, timing.step_height_m)
        liftoff = gait.liftoff_position[leg] - np.array([0.0, 0.0, self.foot_radius_m])
        hip_touchdown = self._hip_at_touchdown(leg, gait, yaw, time_left)
        return FootholdRequest(leg, gait.nominal_foothold[leg], self._fec_hip_height(leg, gait, time_left),
                               gait.base_twist, timing, liftoff, hip_touchdown)

    def _select(self, request: FootholdRequest, yaw: float, map_age_s: float, nominal_world: ArrayLike | None = None
                ) -> Any:
        """The selector's result for ``request`` (around ``nominal_world`` [m] instead of its nominal if given)."""
        return self.selector.select(
            request.leg, request.nominal_world if nominal_world is None else nominal_world, self._grid,
            hip_height_m=request.hip_height_m, twist=request.twist, gait=request.gait, yaw=yaw, map_age_s=map_age_s,
            liftoff_world=request.liftoff_world, hip_touchdown_world=request.hip_touchdown_world)

    def _conclude(self, gait: GaitSnapshot, trigger: str, request: FootholdRequest, result: Any, yaw: float,
                  map_age_s: float, elapsed_s: float) -> FootholdDecision:
        """The decision from the selector's ``result`` for ``request``: the switch hysteresis (a still-safe
        previous selection of the same swing may be kept), then the record. elapsed_s [s]: the selection's
        time so far (the hysteresis check's is added)."""
        leg = request.leg
        start = time.perf_counter()
        previous = self._decisions.get(leg)
        if (previous is not None and previous.step_count == int(gait.step_count[leg])
                and previous.status is VfaStatus.SELECTED and result.status is VfaStatus.SELECTED):
            result = self._keep_if_still_safe(request, gait, result, previous, yaw, map_age_s)
        elapsed = elapsed_s + time.perf_counter() - start
        evaluated = result.status in (VfaStatus.SELECTED, VfaStatus.NO_SAFE_CANDIDATE)
        score = float(getattr(result, "score", 1.0)) if evaluated else 0.0
        count = result.safe_candidates
        return FootholdDecision(
            leg=leg, step_count=int(gait.step_count[leg]), nominal=gait.nominal_foothold[leg].copy(),
            selected=np.asarray(result.selected, dtype=float).copy(), safe_candidate_found=bool(result.any_safe),
            safe_candidates=None if count is None else int(count), score=score, status=result.status,
            trigger=trigger, map_stamp_s=self._map_stamp_s, elapsed_s=elapsed)

    def _keep_if_still_safe(self, request: FootholdRequest, gait: GaitSnapshot, result: Any,
                            previous: FootholdDecision, yaw: float, map_age_s: float) -> Any:
        """``result``, or the previous selection when ``result`` would jump more than ``switch_hysteresis_m``
        away from it for less than ``switch_hysteresis_m`` of distance to the nominal, and the previous
        selection is still safe (the selector, searching around it, returns it)."""
        leg = request.leg
        nominal = gait.nominal_foothold[leg]
        new_distance = float(np.linalg.norm(result.selected[:2] - nominal[:2]))
        old_distance = float(np.linalg.norm(previous.selected[:2] - nominal[:2]))
        hysteresis = self.settings.switch_hysteresis_m
        jump = float(np.linalg.norm(result.selected[:2] - previous.selected[:2]))
        if jump <= hysteresis or old_distance - new_distance > hysteresis:
            return result  # a small move follows the nominal; a large gain is worth a jump
        check = self._select(request, yaw, map_age_s, nominal_world=previous.selected)
        if check.status is not VfaStatus.SELECTED or np.linalg.norm(check.selected[:2] - previous.selected[:2]) > 1e-6:
            return result
        self.counters.kept += 1
        return replace(result, selected=previous.selected.copy(), nominal=np.asarray(nominal, dtype=float).copy(),
                       offset_cells=None)

    def _changes_level_late(self, leg: Leg, gait: GaitSnapshot, previous: FootholdDecision,
                            decision: FootholdDecision) -> bool:
        """True if ``decision`` comes past the level-lock point of the swing and moves the foothold's
        height by more than ``level_lock_dz_m`` from ``previous`` (same swing)."""
        s = self.settings
        if previous.step_count != decision.step_count:
            return False
        swing_s = (1.0 - gait.duty_factor) / gait.step_frequency_hz
        late = gait.time_to_touchdown_s[leg] < (1.0 - s.level_lock_swing_fraction) * swing_s
        return bool(late and abs(decision.selected[2] - previous.selected[2]) > s.level_lock_dz_m)

    def _fec_hip_height(self, leg: Leg, gait: GaitSnapshot, time_left_s: float) -> float:
        """[m] world z of ``leg``'s HAA joint for the FEC: now, or, with ``predict_hip_descent``, at
        touchdown (hip_velocity z over the time left) if that is lower. Why: on the way down the hip is
        lower at touchdown than at the decision, the knee further back and the shin closer to the tread
        edge behind the foot; the two front shin collisions of the 0.2 m/s stairs runs over nine starts
        (6 mm into that edge) were of this kind. Why lower only: using a rising hip's prediction too gave
        6 hind shin collisions in 9 runs at 0.2 m/s (before a riser the hip had not risen as predicted).
        Off by default: on the stairs it removed those front shin collisions but did not measurably improve
        the runs at 0.3-0.5 m/s (README, ViTAL section, stop 24)."""
        height = float(gait.hip_position[leg, 2])
        if not self.settings.predict_hip_descent:
            return height
        return min(height, height + float(gait.hip_velocity[leg, 2]) * max(0.0, float(time_left_s)))

    def _hip_at_touchdown(self, leg: Leg, gait: GaitSnapshot, yaw: float, time_left_s: float) -> FloatArray:
        """(2,) [m] world x, y of ``leg``'s HAA joint at touchdown: moved by the commanded hip velocity
        v + w_z x r (r from the base origin, on the level base) over the time left."""
        c, s = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[c, -s], [s, c]])
        base_xy = self.hips.base_position(gait.hip_position, yaw)[:2]
        r = gait.hip_position[leg, :2] - base_xy
        velocity = rotation @ gait.base_twist[:2] + gait.base_twist[5] * np.array([-r[1], r[0]])
        return gait.hip_position[leg, :2] + velocity * time_left_s

    def _differs(self, previous: FootholdDecision, decision: FootholdDecision) -> bool:
        moved = np.linalg.norm(decision.selected - previous.selected) > self.settings.selection_tolerance_m
        return bool(moved or decision.status is not previous.status)

    def _count(self, decision: FootholdDecision) -> None:
        self.counters.by_status[decision.status.value] += 1
        self.counters.by_trigger[decision.trigger] += 1
        self.counters.adapted += int(decision.adapted)

    def _restart(self) -> None:
        self.counters.restarts += 1
        self.reset()


def _front_minus_hind(hips_xy: FloatArray) -> FloatArray:
    """(2,) mean of the front hips (LF, RF) minus mean of the hind hips (LH, RH)."""
    return 0.5 * (hips_xy[Leg.LF] + hips_xy[Leg.RF] - hips_xy[Leg.LH] - hips_xy[Leg.RH])


def _finite_array(value: object, shape: tuple[int, ...], name: str) -> FloatArray:
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError) as error:
        raise VfaInputError("gait_state_invalid", f"gait state: {name}: not a float array ({error})") from None
    if array.shape != shape:
        raise VfaInputError("gait_state_size", f"gait state: {name} must have shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        bad = sorted({int(i) for i in np.argwhere(~np.isfinite(array))[:, 0]})
        where = [LEGS[i].name for i in bad] if shape[0] == NUM_LEGS and name != "base_twist" else bad
        raise VfaInputError("gait_state_nan", f"gait state: {name} has NaN/inf at {where}")
    return array


__all__ = ["CLOCK_RESET_S", "SELECTORS", "FootholdDecision", "GaitSnapshot", "PlannerCounters", "PlannerSettings",
           "SelectorLike", "VfaPlanner", "make_selector"]
