"""Gait parameters and the gait scheduler: which leg swings when, and how much load a stance leg may take.

Phase convention (per leg): phase 0 is the scheduled lift-off; the leg swings for phase in [0, 1 - duty)
and stands for phase in [1 - duty, 1). ``phase_offsets`` give each leg's lift-off phase within the gait
cycle, in leg order LF, RF, LH, RH. Times are sim time in seconds.

The scheduler is event based: a leg lifts off only when time crosses one of its scheduled lift-off
instants, and a swing, once begun, keeps the duration it started with. So a gait switch (applied at a
cycle boundary of the running gait) never truncates or starts a swing half way; a newly started gait
runs one "preparation" cycle without lift-offs when it starts from standing (or is a statically stable
gait such as the crawl), so the trunk can settle and shift the CoM before the first leg lifts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from tal_control.errors import MotionConfigError
from tal_core.errors import InputError
from tal_core.legs import LEGS, NUM_LEGS

GAIT_NAMES: tuple[str, ...] = ("stand", "crawl", "trot")
_EPS_S = 1e-9  # [s] tolerance when comparing event times


@dataclass(frozen=True)
class GaitParameters:
    """A periodic gait.

    name: "stand", "crawl" or "trot". step_frequency_hz [Hz]: gait cycles per second (for "stand" it
    only clocks when a requested gait switch happens). duty_factor [-]: fraction of the cycle each leg is
    in stance (1 for "stand"). step_height_m [m]: swing apex above the higher of lift-off and touchdown.
    loading_time_s [s]: duration of the load ramps after touchdown and before lift-off.
    phase_offsets [-]: lift-off phase of each leg within the cycle, in [0, 1), order LF, RF, LH, RH.
    """

    name: str
    step_frequency_hz: float
    duty_factor: float
    step_height_m: float
    loading_time_s: float
    phase_offsets: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.name not in GAIT_NAMES:
            raise MotionConfigError(f"gait name {self.name!r} is not one of {', '.join(GAIT_NAMES)}")
        where = f"gait {self.name!r}"
        for key in ("step_frequency_hz", "duty_factor", "step_height_m", "loading_time_s"):
            if not math.isfinite(getattr(self, key)):
                raise MotionConfigError(f"{where}: {key} must be finite, got {getattr(self, key)!r}")
        if self.step_frequency_hz <= 0.0:
            raise MotionConfigError(f"{where}: step_frequency_hz must be > 0, got {self.step_frequency_hz}")
        if (self.name == "stand") != (self.duty_factor == 1.0):
            raise MotionConfigError(f"{where}: duty_factor must be 1 exactly for 'stand' and in (0, 1) "
                                    f"for a moving gait, got {self.duty_factor}")
        if not 0.0 < self.duty_factor <= 1.0:
            raise MotionConfigError(f"{where}: duty_factor must be in (0, 1], got {self.duty_factor}")
        if self.step_height_m < 0.0 or (self.name != "stand" and self.step_height_m == 0.0):
            raise MotionConfigError(f"{where}: step_height_m must be > 0 (>= 0 for 'stand'), "
                                    f"got {self.step_height_m}")
        if self.loading_time_s < 0.0 or (self.name != "stand"
                                         and 2.0 * self.loading_time_s > self.stance_duration_s):
            raise MotionConfigError(f"{where}: loading_time_s must be in [0, stance duration / 2 = "
                                    f"{self.stance_duration_s / 2.0:.4g} s], got {self.loading_time_s}")
        offsets = tuple(float(v) for v in self.phase_offsets)
        if len(offsets) != NUM_LEGS or not all(0.0 <= v < 1.0 for v in offsets):
            raise MotionConfigError(f"{where}: phase_offsets must be {NUM_LEGS} values in [0, 1) "
                                    f"(LF, RF, LH, RH), got {self.phase_offsets!r}")
        object.__setattr__(self, "phase_offsets", offsets)

    @property
    def is_standing(self) -> bool:
        return self.duty_factor >= 1.0

    @property
    def cycle_duration_s(self) -> float:
        """[s] duration of one gait cycle."""
        return 1.0 / self.step_frequency_hz

    @property
    def stance_duration_s(self) -> float:
        """[s] duration of one stance phase of a leg."""
        return self.duty_factor * self.cycle_duration_s

    @property
    def swing_duration_s(self) -> float:
        """[s] duration of one swing phase (0 when standing)."""
        return (1.0 - self.duty_factor) * self.cycle_duration_s

    def swinging_at(self, cycle_phase: float) -> np.ndarray:
        """(4,) bool: which legs the schedule has in swing at ``cycle_phase`` [-] of the cycle."""
        leg_phase = (cycle_phase - np.asarray(self.phase_offsets)) % 1.0
        return leg_phase < 1.0 - self.duty_factor

    @property
    def max_simultaneous_swings(self) -> int:
        """Largest number of legs swinging at the same time over a cycle."""
        if self.is_standing:
            return 0
        return int(max(self.swinging_at(offset).sum() for offset in self.phase_offsets))

    @property
    def is_statically_stable(self) -> bool:
        """A moving gait in which at most one leg swings at a time (three legs always support)."""
        return not self.is_standing and self.max_simultaneous_swings <= 1


STAND = GaitParameters("stand", step_frequency_hz=1.0, duty_factor=1.0, step_height_m=0.0,
                       loading_time_s=0.1)
# Crawl: LH, LF, RH, RF; 0.4 s swings and 0.1 s four-leg phases between them (the trunk shifts the CoM).
CRAWL = GaitParameters("crawl", step_frequency_hz=0.5, duty_factor=0.8, step_height_m=0.12,
                       loading_time_s=0.1, phase_offsets=(0.25, 0.75, 0.0, 0.5))
# Trot: diagonal pairs LF+RH then RF+LH; 0.27 s swings, 0.067 s four-leg phases at each exchange.
TROT = GaitParameters("trot", step_frequency_hz=1.5, duty_factor=0.6, step_height_m=0.10,
                      loading_time_s=0.05, phase_offsets=(0.0, 0.5, 0.5, 0.0))
PRESETS: dict[str, GaitParameters] = {"stand": STAND, "crawl": CRAWL, "trot": TROT}


@dataclass(frozen=True, eq=False)
class GaitPhase:
    """Gait state at one time; per-leg arrays (4,) in leg order LF, RF, LH, RH, read-only.

    ``phase`` is the leg's nominal phase in the running gait's clock (0 = scheduled lift-off); ``swing``
    is what the leg actually does (after a switch a leg may finish a swing begun under the old gait, and
    no leg lifts off during a preparation cycle). ``time_to_touchdown_s`` [s] is the remaining swing time
    (0 in stance); ``time_to_liftoff_s`` [s] the remaining stance time before the next scheduled lift-off
    (0 in swing, inf when none is scheduled). ``swing_duration_s`` [s]: the current swing's duration for
    swinging legs, the next swing's for stance legs (0 if none). ``step_count``: swings started so far.
    ``load_factor`` in [0, 1]: 0 in swing, ramps to 1 over loading_time_s after touchdown and back to 0
    over loading_time_s before lift-off. ``liftoff_event``/``touchdown_event``: happened in this update.
    ``liftoff_time_s``/``touchdown_time_s`` [s]: time of the last lift-off/touchdown (-inf if none yet).
    """

    t_s: float
    gait: GaitParameters
    pending_gait: GaitParameters | None
    cycle_phase: float
    gait_start_time_s: float
    preparing: bool
    phase: np.ndarray
    swing: np.ndarray
    swing_progress: np.ndarray
    swing_duration_s: np.ndarray
    time_to_touchdown_s: np.ndarray
    time_to_liftoff_s: np.ndarray
    step_count: np.ndarray
    load_factor: np.ndarray
    liftoff_event: np.ndarray
    touchdown_event: np.ndarray
    liftoff_time_s: np.ndarray
    touchdown_time_s: np.ndarray

    def __post_init__(self) -> None:
        for value in vars(self).values():
            if isinstance(value, np.ndarray):
                value.setflags(write=False)

    @property
    def stance(self) -> np.ndarray:
        """(4,) bool, True for legs on the ground."""
        return ~self.swing


@dataclass
class _Schedule:
    """A gait running from ``origin`` [s]; lift-offs are allowed from ``allowed_from`` [s] on."""

    gait: GaitParameters
    origin: float
    allowed_from: float

    def first_liftoff(self, leg: int, t_from: float) -> float:
        """Earliest scheduled lift-off time [s] of ``leg`` at or after ``t_from``; inf if none."""
        if self.gait.is_standing:
            return math.inf
        period = self.gait.cycle_duration_s
        offset = self.gait.phase_offsets[leg]
        t_min = max(t_from, self.allowed_from)
        n = math.ceil((t_min - self.origin) / period - offset - _EPS_S / period)
        return self.origin + (n + offset) * period

    def next_boundary(self, t_from: float) -> float:
        """First cycle boundary [s] at or after ``t_from``."""
        period = self.gait.cycle_duration_s
        return self.origin + math.ceil((t_from - self.origin) / period - _EPS_S / period) * period


@dataclass
class _LegState:
    swinging: bool = False
    liftoff_time: float = -math.inf
    touchdown_time: float = -math.inf  # last touchdown
    planned_touchdown: float = math.inf  # end of the current swing
    swing_duration: float = 0.0
    steps: int = 0
    next_liftoff: float = math.inf
    next_swing_duration: float = 0.0
    load_up_s: float = 0.0  # loading time of the gait at the last touchdown
    load_down_s: float = 0.0  # loading time of the gait of the next lift-off
    lifted: bool = False  # lifted off / touched down in the current update
    landed: bool = False


class GaitScheduler:
    """Turns sim time into a ``GaitPhase``; switches gaits only at cycle boundaries.

    ``update(t_s)`` must be called with strictly increasing times [s]. The first update starts the
    initial gait (with a preparation cycle unless it is "stand"). ``set_gait`` requests a switch applied
    at the first cycle boundary of the running gait that is at least one loading time away.
    """

    def __init__(self, params: GaitParameters) -> None:
        if not isinstance(params, GaitParameters):
            raise MotionConfigError(f"GaitScheduler needs GaitParameters, got {type(params).__name__}")
        self._initial = params
        self._active: _Schedule | None = None
        self._pending: _Schedule | None = None
        self._legs = [_LegState() for _ in LEGS]
        self._t_prev: float | None = None

    @property
    def gait(self) -> GaitParameters:
        """The running gait (the initial one before the first update)."""
        return self._initial if self._active is None else self._active.gait

    @property
    def pending_gait(self) -> GaitParameters | None:
        return None if self._pending is None else self._pending.gait

    def set_gait(self, params: GaitParameters) -> None:
        """Request ``params``; applied at the next suitable cycle boundary (see the class docstring)."""
        if not isinstance(params, GaitParameters):
            raise MotionConfigError(f"set_gait needs GaitParameters, got {type(params).__name__}")
        if self._active is None or self._t_prev is None:
            self._initial = params
            return
        current = self._active.gait
        self._pending = None
        if params != current:
            lead = max(current.loading_time_s, params.loading_time_s)
            switch = self._active.next_boundary(self._t_prev + lead)
            prepare = current.is_standing or params.is_statically_stable
            allowed = switch + (params.cycle_duration_s if prepare else 0.0)
            self._pending = _Schedule(params, switch, allowed)
        for index, leg in enumerate(self._legs):
            if not leg.swinging:
                self._plan_next_liftoff(index, self._t_prev)

    def set_step_height(self, step_height_m: float) -> None:
        """Swing apex [m] of the running gait (and of a pending one) from the next lift-off on. Not a gait
        switch: the schedule and the swings under way are untouched. MotionConfigError when a gait
        refuses the height (0 for a moving gait)."""
        schedules = [s for s in (self._active, self._pending) if s is not None]
        height = float(step_height_m)
        gaits = [replace(gait, step_height_m=height) for gait in (self._initial, *(s.gait for s in schedules))]
        self._initial = gaits[0]
        for schedule, gait in zip(schedules, gaits[1:], strict=True):
            schedule.gait = gait

    def update(self, t_s: float) -> GaitPhase:
        """Advance to time ``t_s`` [s] (strictly after the previous call) and return the gait state."""
        t = float(t_s)
        if not math.isfinite(t):
            raise InputError(f"gait scheduler: time must be finite, got {t_s!r}")
        if self._t_prev is not None and t <= self._t_prev:
            raise InputError(f"gait scheduler: time {t:.6f} s is not after the previous {self._t_prev:.6f} s")
        for leg in self._legs:
            leg.lifted = leg.landed = False
        if self._active is None:
            gait = self._initial
            prepare = 0.0 if gait.is_standing else gait.cycle_duration_s
            self._active = _Schedule(gait, t, t + prepare)
            for index in range(NUM_LEGS):
                self._plan_next_liftoff(index, t)
        else:
            self._process_events(t)
        self._t_prev = t
        return self._phase(t)

    # --- events ---
    def _process_events(self, t: float) -> None:
        """Apply touchdowns, the gait switch and lift-offs due up to ``t`` in time order."""
        while True:
            candidates: list[tuple[float, int, int]] = []  # (time, kind order, leg)
            for index, leg in enumerate(self._legs):
                if leg.swinging and leg.planned_touchdown <= t + _EPS_S:
                    candidates.append((leg.planned_touchdown, 0, index))
                elif not leg.swinging and leg.next_liftoff <= t + _EPS_S:
                    candidates.append((leg.next_liftoff, 2, index))
            if self._pending is not None and self._pending.origin <= t + _EPS_S:
                candidates.append((self._pending.origin, 1, -1))
            if not candidates:
                return
            time, kind, index = min(candidates)
            if kind == 0:
                self._touchdown(index, time)
            elif kind == 1:
                self._switch(time)
            else:
                self._liftoff(index, time)

    def _touchdown(self, index: int, time: float) -> None:
        leg = self._legs[index]
        leg.swinging = False
        leg.touchdown_time = time
        leg.load_up_s = self.gait.loading_time_s
        leg.landed = True
        self._plan_next_liftoff(index, time)

    def _switch(self, time: float) -> None:
        assert self._pending is not None
        self._active, self._pending = self._pending, None
        for index, leg in enumerate(self._legs):
            if not leg.swinging:
                self._plan_next_liftoff(index, time)

    def _liftoff(self, index: int, time: float) -> None:
        leg = self._legs[index]
        leg.swinging = True
        leg.liftoff_time = time
        leg.swing_duration = leg.next_swing_duration
        leg.planned_touchdown = time + leg.swing_duration
        leg.steps += 1
        leg.lifted = True
        leg.next_liftoff = math.inf

    def _plan_next_liftoff(self, index: int, t_from: float) -> None:
        """Store the next lift-off of a stance leg, looking past a pending switch into the new gait."""
        assert self._active is not None
        leg = self._legs[index]
        schedule = self._active
        time = schedule.first_liftoff(index, t_from)
        if self._pending is not None and time >= self._pending.origin - _EPS_S:
            schedule = self._pending
            time = schedule.first_liftoff(index, max(t_from, schedule.origin))
        leg.next_liftoff = time
        leg.next_swing_duration = schedule.gait.swing_duration_s if math.isfinite(time) else 0.0
        leg.load_down_s = schedule.gait.loading_time_s

    # --- output ---
    def _phase(self, t: float) -> GaitPhase:
        assert self._active is not None
        gait = self._active.gait
        cycle_phase = ((t - self._active.origin) * gait.step_frequency_hz) % 1.0
        rows = []  # per leg: swing duration, progress, time to touchdown, time to lift-off, load
        for leg in self._legs:
            if leg.swinging:
                progress = min(1.0, max(0.0, (t - leg.liftoff_time) / leg.swing_duration))
                rows.append((leg.swing_duration, progress, max(0.0, leg.planned_touchdown - t), 0.0, 0.0))
            else:
                to_liftoff = max(0.0, leg.next_liftoff - t)
                load = _load_factor(t - leg.touchdown_time, to_liftoff, leg.load_up_s, leg.load_down_s)
                rows.append((leg.next_swing_duration, 0.0, 0.0, to_liftoff, load))
        durations, progress, to_touchdown, to_liftoff, load = np.array(rows).T.copy()
        legs = self._legs
        return GaitPhase(
            t_s=t, gait=gait, pending_gait=self.pending_gait, cycle_phase=cycle_phase,
            gait_start_time_s=self._active.origin,
            preparing=t < self._active.allowed_from and not gait.is_standing,
            phase=(cycle_phase - np.asarray(gait.phase_offsets)) % 1.0,
            swing=np.array([leg.swinging for leg in legs]), swing_progress=progress,
            swing_duration_s=durations, time_to_touchdown_s=to_touchdown, time_to_liftoff_s=to_liftoff,
            step_count=np.array([leg.steps for leg in legs], dtype=np.int64), load_factor=load,
            liftoff_event=np.array([leg.lifted for leg in legs]),
            touchdown_event=np.array([leg.landed for leg in legs]),
            liftoff_time_s=np.array([leg.liftoff_time for leg in legs]),
            touchdown_time_s=np.array([leg.touchdown_time for leg in legs]),
        )


def _load_factor(since_touchdown_s: float, to_liftoff_s: float, up_s: float, down_s: float) -> float:
    """Stance load factor in [0, 1]: linear ramps after touchdown and before lift-off."""
    up = 1.0 if up_s <= 0.0 else since_touchdown_s / up_s
    down = 1.0 if down_s <= 0.0 else to_liftoff_s / down_s
    return float(min(1.0, max(0.0, min(up, down))))
