"""The Terrain Compliance Estimator's per-tick driver (ROS-free): which joint samples are TCE ticks, which
base state a tick uses, how the robot state for the contact-state estimation is assembled and what happens
to feet outside the known terrain. The ``tce`` node and every offline runner (tal_lab: the in-process closed
loop, the bag replay, the estimation experiments) drive ``TerrainComplianceEstimator`` through it.

A tick (``step``) takes the base state (world frame: ground truth as the thesis' motion capture, or the
state estimate) and the joint state, finite-differences the generalised velocities of consecutive ticks
for the leg dynamics (across at most one lost tick: ``MAX_ACCELERATION_GAP_PERIODS``) with the mean joint
torque over the same interval (``average_torque``: the samples between two ticks are read for their torque),
estimates the contact states against the undeformed terrain (``height``, optional ``normal``) and refits the
stance legs. After a
longer gap the accelerations are unknown, the force is its static part only and a swing leg can read as
loaded (its airborne penetration in the window turned rigid-ground fits soft when a starved real-time tce lost
ticks): such a tick does not feed the fit (counted in ``ticks_without_acceleration``), its estimates are the
previous ones. Lost ticks (a gap of g periods: g - 1 of them, ``lost_ticks``) age the stance legs' windows as
their samples would have, so a window spans the time the thesis' 250 samples at 250 Hz do, whatever the rate
the tce keeps up with. A stance foot whose penetration is unknown (outside the heightmap) gives no sample: it is fed
as not in contact and counted in ``samples_outside_map``.

Streamed (``add_joints``, as the node ticks): ticks fall on the sim-time grid k * period_s of the joint-state
stamps once a base state and the terrain have arrived, and use the latest base state unless it is older than
``stale_state_periods`` periods (the tick is skipped, counted in ``stale_ticks``). A joint state that cannot
be read or a tick the TCE refuses is counted in ``rejected`` and reported to ``on_reject``.

With ``base_period_s`` (the base state's publishing period; a node's default) a tick waits for the base state
of its own stamp, the newest on the base publisher's grid at or before it, so the result does not depend on
whether the joint state or the base state arrives first (lockstep runs repeat bit for bit). A waiting tick
is computed when that base state arrives (``set_base`` returns it, with the base state of its own stamp even
when a newer one came first) or, with whatever base state is there (counted in ``late_base_ticks``), on the
first joint sample more than ``max_defer_s`` after it: the robot moved on. Waiting ticks queue in stamp order:
the next tick's sample may come before the waiting one's base state (another topic; in a lockstep tour on the
estimate 0.6 % of the ticks), and it then waits behind it; a third waiting tick (``MAX_WAITING_TICKS``) runs the
oldest with what is there. Every tick is answered: a waiting tick that the next one replaced unanswered
stalled lockstep tours on the estimate (the estimator's tick waits for the TCE's answer one period back, and
the TCE's next tick for that estimator tick's estimate), and one answered with the latest base state when its
successor came made those tours differ from run to run.

Heightmaps streamed with ``add_heightmap`` come into use at the first tick at or after their stamp. With
``heightmap_period_s`` (the publisher's period on the sim-time grid, as the bridge's) a tick also waits for
the map of its grid point, so that it does not depend on whether the map or the joint state arrived first
(DDS gives no order between topics; the heightmaps are robot-centred, so the terrain under a foot differs
slightly from one map to the next); maps that came after the tick that should have used them are counted in
``late_heightmaps``, ticks run without theirs in ``late_heightmap_ticks``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from tal_core.errors import InputError
from tal_core.robot_model import RobotModel
from tal_core.state import BaseState
from tal_core.ticks import TICK_TOLERANCE_NS, RecentByStamp, StampedInbox, reaches_tick, tick_after

from .streaming import JointArrays
from .tce import (
    ContactSample,
    FiniteDifferenceAcceleration,
    HeightFunction,
    LegEstimate,
    NormalFunction,
    TceSettings,
    TerrainComplianceEstimator,
)

LOST_TICKS_AGE_LIMIT = 250
"""Longer gaps (a pause, a restart) do not age the windows."""

MAX_AVERAGED_TORQUES = 16
"""Joint samples between two ticks whose torques a tick averages (the newest)."""

MAX_ACCELERATION_GAP_PERIODS = 2.5
"""Ticks between two joint samples over which the legs' accelerations are still finite-differenced."""

MAX_WAITING_TICKS = 2
"""Ticks that may wait at once for their base state or map (in lockstep the wbc waits for the answer to the
previous tick, so a third sample never comes first); a third runs the oldest with what is there (late)."""

KEPT_BASE_STATES = 16
"""Recent base states kept by stamp: a waiting tick takes the one of its own stamp."""


@dataclass(frozen=True)
class TceTick:
    """One TCE tick: the contact samples the fit saw (leg order) and a snapshot of the per-leg estimates,
    normal direction and (estimate_tangential) tangential."""

    t_s: float
    samples: tuple[ContactSample, ...]
    estimates: tuple[LegEstimate, ...]
    tangential: tuple[LegEstimate, ...] | None
    stamp_ns: int | None = None  # the joint sample's stamp, streamed ticks only

    @property
    def stiffness_n_per_m(self) -> np.ndarray:
        return np.array([e.stiffness_n_per_m for e in self.estimates])

    @property
    def damping_ns_per_m(self) -> np.ndarray:
        return np.array([e.damping_ns_per_m for e in self.estimates])

    @property
    def confidence(self) -> np.ndarray:
        return np.array([e.confidence for e in self.estimates])

    @property
    def valid(self) -> np.ndarray:
        return np.array([e.valid for e in self.estimates])

    @property
    def in_contact(self) -> np.ndarray:
        return np.array([s.in_contact for s in self.samples])


class TceDriver:
    """Drives a TerrainComplianceEstimator tick by tick; see the module docstring. ``period_s`` [s] is the
    tick period (grid and finite differences), ``stale_state_periods`` [-] the oldest usable base state."""

    def __init__(self, model: RobotModel, settings: TceSettings | None = None, *, period_s: float = 0.004,
                 stale_state_periods: int = 3, on_reject: Callable[[Exception], None] | None = None,
                 base_period_s: float | None = None, max_defer_s: float = 0.0,
                 heightmap_period_s: float = 0.0, average_torque: bool = True) -> None:
        if base_period_s is not None and base_period_s <= 0.0:
            raise InputError(f"TceDriver: base_period_s must be > 0 or None, got {base_period_s!r}")
        if max_defer_s < 0.0:
            raise InputError(f"TceDriver: max_defer_s must be >= 0, got {max_defer_s!r}")
        if not (math.isfinite(heightmap_period_s) and heightmap_period_s >= 0.0):
            raise InputError(f"TceDriver: heightmap_period_s must be finite and >= 0, got {heightmap_period_s!r}")
        self.model = model
        self.tce = TerrainComplianceEstimator(model, settings)
        self.period_ns = round(period_s * 1e9)
        self.stale_state_periods = stale_state_periods
        self.on_reject = on_reject
        self.base_period_ns = None if base_period_s is None else round(base_period_s * 1e9)
        self.max_defer_ns = round(max_defer_s * 1e9)
        self.height: HeightFunction | None = None
        self.normal: NormalFunction | None = None
        self.ticks = 0
        self.samples_outside_map = 0
        self.stale_ticks = 0
        self.late_base_ticks = 0
        self.ticks_without_acceleration = 0
        self.lost_ticks = 0
        self._last_step_s: float | None = None
        self.late_heightmap_ticks = 0
        self._terrain = StampedInbox(0, period_ns=round(heightmap_period_s * 1e9))
        self.rejected = 0
        # Finite differences across one lost tick still give the legs' mean acceleration (a tce behind its
        # inputs on a busy machine loses some); after a longer gap the tick's samples skip the fit (``step``).
        self._accelerations = FiniteDifferenceAcceleration(max_gap_s=MAX_ACCELERATION_GAP_PERIODS * period_s)
        self._next_tick_ns = 0
        self._bases = RecentByStamp(KEPT_BASE_STATES)   # recent base states by stamp
        self._pending: deque[tuple[int, float, tuple[np.ndarray, np.ndarray, np.ndarray]]] = deque()
        # The joint torques of the samples between two ticks (``average_torque``): their mean is the torque of
        # the interval whose finite-differenced acceleration the tick uses.
        self.average_torque = bool(average_torque)
        self._torques: list[np.ndarray] = []
        self._torque_last_ns = -1

    @property
    def settings(self) -> TceSettings:
        return self.tce.settings

    def reconfigure(self, settings: TceSettings) -> None:
        """New thresholds from the next tick (``TerrainComplianceEstimator.reconfigure``)."""
        self.tce.reconfigure(settings)

    def set_terrain(self, height: HeightFunction, normal: NormalFunction | None = None) -> None:
        """The undeformed terrain: height(x, y) [m] (NaN where unknown) and, optionally, the unit normal."""
        self.height, self.normal = height, normal

    @property
    def late_heightmaps(self) -> int:
        """Streamed maps that arrived after the tick that should have used them."""
        return self._terrain.late

    @property
    def missed_heightmaps(self) -> int:
        """Maps due at a tick that never came while a newer one did (``StampedInbox.missed``)."""
        return self._terrain.missed

    def add_heightmap(self, stamp_ns: int, height: HeightFunction, normal: NormalFunction | None = None
                      ) -> list[TceTick]:
        """A streamed map (see the module docstring): in use from the first tick at or after ``stamp_ns``; the
        waiting ticks it completes, oldest first."""
        self._terrain.add(stamp_ns, (height, normal))
        return self._run_ready()

    def set_base(self, stamp_ns: int, base: BaseState) -> list[TceTick]:
        """A base state (world frame) and its stamp; the waiting ticks it completes, oldest first."""
        self._bases.add(stamp_ns, base)
        return self._run_ready()

    def _ready(self, stamp_ns: int) -> bool:
        """Whether the base state and the map a tick at ``stamp_ns`` waits for have arrived (a newer base state
        than its own: its own will not come)."""
        newest = self._bases.newest_ns
        return (newest is not None and newest >= self._expected_base_stamp(stamp_ns)
                and self._terrain.awaited(stamp_ns) is None)

    def _base_for(self, stamp_ns: int) -> tuple[int, BaseState] | None:
        """The base state a tick at ``stamp_ns`` uses: that of its own stamp when it came, else the newest."""
        if self.base_period_ns is not None:
            expected = self._expected_base_stamp(stamp_ns)
            if expected in self._bases:
                return expected, self._bases.get(expected)
        return self._bases.newest()

    def _run_ready(self) -> list[TceTick]:
        out = []
        while self._pending and self._ready(self._pending[0][0]):
            out.append(self._tick(*self._pending.popleft()))
        return [tick for tick in out if tick is not None]

    def _use_terrain(self, stamp_ns: int) -> None:
        due = self._terrain.due(stamp_ns)
        if due:
            self.height, self.normal = due[-1][1]

    def wants_joints(self, stamp_ns: int) -> bool:
        """Whether ``add_joints`` would do anything with a sample stamped ``stamp_ns`` (a tick, the end of a
        waiting tick's wait, or a torque sample of the interval before the next tick): a node may skip the
        others."""
        return (reaches_tick(stamp_ns, self._next_tick_ns) or self._overdue(stamp_ns)
                or (self.average_torque and stamp_ns > self._torque_last_ns))

    def add_joints(self, stamp_ns: int, read: Callable[[], JointArrays], t_s: float | None = None) -> TceTick | None:
        """``add_joints_all`` for callers that publish one answer per sample: the newest tick computed."""
        ticks = self.add_joints_all(stamp_ns, read, t_s)
        return ticks[-1] if ticks else None

    def add_joints_all(self, stamp_ns: int, read: Callable[[], JointArrays],
                       t_s: float | None = None) -> list[TceTick]:
        """One joint-state sample; the ticks computed on it, oldest first (see the module docstring): a
        waiting one whose base state did not come in time (or whose successor is due), and its own. ``read()``
        gives the arrays (called only for a tick). ``t_s``: the tick's time [s] (default stamp_ns * 1e-9)."""
        out: list[TceTick | None] = []
        while self._overdue(stamp_ns):
            out.append(self._run_pending(late=True))
        waits = self.base_period_ns is not None
        if not reaches_tick(stamp_ns, self._next_tick_ns):
            if self.average_torque and stamp_ns > self._torque_last_ns:
                self._add_torque(stamp_ns, read)
            return [tick for tick in out if tick is not None]
        map_awaited = self._terrain.awaited(stamp_ns) is not None
        no_terrain = self.height is None and not map_awaited and not self._terrain.has_due(stamp_ns)
        if no_terrain or (self._bases.newest_ns is None and not waits):
            return [tick for tick in out if tick is not None]
        while len(self._pending) >= MAX_WAITING_TICKS:   # too many wait: the oldest runs with what is here
            out.append(self._run_pending(late=True))
        self._next_tick_ns = tick_after(stamp_ns, self.period_ns)
        self._torque_last_ns = max(self._torque_last_ns, stamp_ns)
        t = stamp_ns * 1e-9 if t_s is None else t_s
        arrays = self._read(read)
        if arrays is not None:
            if self._pending or (not self._ready(stamp_ns) and (waits or map_awaited)):
                self._pending.append((stamp_ns, t, arrays))   # behind the waiting ones, in stamp order
            else:
                out.append(self._tick(stamp_ns, t, arrays))
        return [tick for tick in out if tick is not None]

    def _expected_base_stamp(self, stamp_ns: int) -> int:
        """The base state a tick at ``stamp_ns`` waits for (its stamp; 0 when it takes the latest)."""
        if self.base_period_ns is None:
            return 0
        return ((stamp_ns + TICK_TOLERANCE_NS) // self.base_period_ns) * self.base_period_ns

    def _overdue(self, stamp_ns: int) -> bool:
        return bool(self._pending) and stamp_ns - self._pending[0][0] > self.max_defer_ns

    def _run_pending(self, late: bool = False) -> TceTick | None:
        """The oldest waiting tick, now (late: without what it waited for, counted)."""
        stamp_ns, t_s, arrays = self._pending.popleft()
        if late and not self._ready(stamp_ns):
            if self._terrain.awaited(stamp_ns) is not None:
                self.late_heightmap_ticks += 1
            else:
                self.late_base_ticks += 1
        return self._tick(stamp_ns, t_s, arrays)

    def _read(self, read: Callable[[], JointArrays]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """A tick's joint arrays; with ``average_torque`` its torque is the mean over the samples since the
        previous tick (this one included)."""
        try:
            q, qd, tau = read()
        except (InputError, ValueError) as exc:
            self._rejected(exc)
            return None
        if self._torques and tau is not None:
            # The last torque plus the mean deviation of the interval's: exactly the last when the command
            # held over the interval (lockstep stays bit for bit what it was).
            tau = tau + sum(earlier - tau for earlier in self._torques) / (len(self._torques) + 1)
        self._torques.clear()
        return q, qd, tau

    def _add_torque(self, stamp_ns: int, read: Callable[[], JointArrays]) -> None:
        """A joint sample between two ticks: its torque enters the next tick's mean. The torque a sample
        carries is what the actuators delivered over the period before it; the tick's finite-differenced
        acceleration is the mean over the interval since the previous tick, so the dynamics that give the
        feet's forces must take the mean torque over the same interval. On a robot (or a bridge following the
        wall clock) the command changes within the interval, wherever it arrives: with the last sample's
        torque alone a starved or jittered tce read rigid ground as 2e5-7e5 N/m (1.6e6-2e6 in lockstep, where
        a command holds over the whole interval)."""
        try:
            tau = read()[2]
        except (InputError, ValueError) as exc:
            self._rejected(exc)
            return
        self._torque_last_ns = stamp_ns
        if tau is not None and np.all(np.isfinite(tau)):
            if len(self._torques) >= MAX_AVERAGED_TORQUES:
                del self._torques[0]   # a long gap: its tick has no acceleration anyway
            self._torques.append(np.array(tau, dtype=float))

    def _rejected(self, exc: Exception) -> None:
        self.rejected += 1
        if self.on_reject is not None:
            self.on_reject(exc)

    def _tick(self, stamp_ns: int, t_s: float, arrays: tuple[np.ndarray, np.ndarray, np.ndarray]) -> TceTick | None:
        self._use_terrain(stamp_ns)
        base = self._base_for(stamp_ns)
        if base is None or stamp_ns - base[0] > self.stale_state_periods * self.period_ns:
            self.stale_ticks += 1
            return None
        try:
            tick = self.step(t_s, base[1], *arrays)
        except (InputError, ValueError) as exc:
            self._rejected(exc)
            return None
        return replace(tick, stamp_ns=stamp_ns)

    def step(self, t_s: float, base: BaseState, joint_position: np.ndarray, joint_velocity: np.ndarray,
             joint_torque: np.ndarray) -> TceTick:
        """One tick at ``t_s`` [s] on ``base`` and the joint state; InputError for unusable input."""
        if self.height is None:
            raise InputError("TCE: no terrain (set_terrain) for the tick")
        m = self.model
        q = m.make_q(base.position, base.quat_xyzw, joint_position)
        v = m.make_v(base.linear_velocity, base.angular_velocity, joint_velocity, base.quat_xyzw)
        vdot = self._accelerations.update(t_s, v)
        samples = self.tce.contact_states(q, v, joint_torque, self.height, self.normal, vdot=vdot)
        lost = 0 if self._last_step_s is None else round((t_s - self._last_step_s) * 1e9 / self.period_ns) - 1
        self._last_step_s = t_s
        if 0 < lost <= LOST_TICKS_AGE_LIMIT:
            # Lost ticks age the stance legs' windows as their samples would have, so that a window still spans
            # the time of the thesis' 250 samples at 250 Hz (fed at 100 Hz it held a patch's stiffness 2.5
            # times as long, over the rigid metre before the stairs).
            self.tce.skip([s.in_contact for s in samples], lost)
            self.lost_ticks += lost
        usable = []
        for sample in samples:
            if sample.in_contact and not math.isfinite(sample.penetration_m):
                self.samples_outside_map += 1
                usable.append(ContactSample(False, sample.force_n, sample.normal, 0.0, 0.0))
            else:
                usable.append(sample)
        if vdot is None and self.ticks > 0:
            # After a gap the legs' accelerations are unknown and the force is the static part only: a swing
            # leg can read as loaded, its airborne penetration would enter the window (on rigid ground a few
            # such samples turned the fit soft). The fit skips the tick; the estimates stand.
            self.ticks_without_acceleration += 1
            estimates = self.tce.estimates
        else:
            estimates = self.tce.update(usable)
        tangential = self.tce.tangential_estimates
        self.ticks += 1
        return TceTick(t_s, tuple(usable), tuple(replace(e) for e in estimates),
                       None if tangential is None else tuple(replace(e) for e in tangential))
