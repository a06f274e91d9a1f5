"""The state estimator's streaming tick (ROS-free): the one place that decides when the estimator ticks,
which samples a tick uses, when it restarts and which input it rejects. The ``state_estimator`` node and
every offline runner (tal_lab: bag replay, recorded arrays, the in-process closed loop) feed it samples one
at a time, so live and offline give the same estimates.

IMU and joint-state samples (1 kHz each) arrive separately and in no fixed order. Ticks fall on the sim-time
grid k * period_s of the joint-state stamps: the first joint sample at or past the next grid point is that
tick's sample. It stays *pending* until the IMU sample of its stamp has arrived (the pairing by stamp), or
until the next grid sample arrives (then it runs with the IMU samples that did come). A tick's IMU input is
the mean of the IMU samples in (previous tick, tick] (pre-integration; when IMU stamps jitter apart from the
joints' and no sample came in that window, the sample after the tick, within a period, counted in
``nearest_imu_ticks``); the first tick initialises the
filter (at a given pose, or standing on flat ground), later ones update it.

Rejected and counted by reason in ``rejections``: IMU samples with NaN or at the sensor range (imu_nan,
imu_saturated), an IMU stamp going backwards (imu_out_of_order), a joint state that cannot be read
(joints), a tick with no IMU sample ever (no_imu) and a tick the filter refuses (its reason). A tick whose
IMU samples were all rejected reuses the previous mean (``held_imu_ticks``). A repeated stamp (a simulator
resends its first state until a controller answers) is counted in ``duplicates``; a repeated joint sample
of the last tick gives a "repeat" output so a node can answer it again. A stamp more than CLOCK_RESET_NS
behind the last one is a restarted clock: the estimator starts again (``restarts``).

Robots without joint torques or joint velocities: with a sensor ``contact_source`` (leg odometry settings) a
tick needs the feet's sensor values, given with the joint sample (``add_joints(..., foot_contact=...)``, one
message or row carrying both) or as a stream of their own (``add_contacts``, paired by stamp as the IMU: a
tick waits for a contact sample at or past its stamp, or for the next grid sample, and uses the latest one
at or before its stamp; rejected: contacts, no_contacts). A joint state whose ``read()`` gives no
velocities (None) gets them from ``JointVelocityFilter`` (finite difference + low-pass at
``joint_velocity_cutoff_hz``); from the first such sample on, every joint sample is read and feeds the
filter, not only the ticks'. Stamps with jitter: ``tick_tolerance_s`` (settings) is how early a sample may
be and still take a tick's grid point.

Terrain impedance (the TCE's answer, stamped with the TCE tick it was computed on): set ``impedance`` to take
whatever arrived last, or stream it with ``add_impedance`` and an ``impedance_period_s`` (the TCE's period):
then a tick uses the impedance of the TCE tick at least one TCE period before it (``StampedInbox``) and waits
for it, so what a tick uses does not depend on how fast the TCE answered (lockstep runs on the estimate repeat
bit for bit; the TCE's tick waits for the estimate of its own stamp, so the lag keeps the two from waiting on
each other). A tick still waiting for it when a joint sample more than ``impedance_max_defer_s`` after it
arrives (0: the next grid sample) runs with the impedance it has, counted in ``late_impedance_ticks`` (the
TCE is slower than the robot, or gone); later ticks queue behind it, in order.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tal_core.errors import InputError
from tal_core.legs import NUM_LEGS
from tal_core.robot_model import RobotModel
from tal_core.ticks import CLOCK_RESET_NS, StampedInbox, reaches_tick, tick_after

from .joint_velocity import JointVelocityFilter
from .leg_odometry import LegImpedance
from .state_estimator import EstimatorInputError, StateEstimate, StateEstimator, StateEstimatorSettings

JointArrays = tuple[np.ndarray, "np.ndarray | None", "np.ndarray | None"]
"""Joint positions [rad], velocities [rad/s] and measured torques [N m], canonical order; velocities None:
derive them; torques None: none measured (a sensor contact source)."""
_Pending = tuple[int, float, np.ndarray, "np.ndarray | None", "np.ndarray | None", "np.ndarray | None"]


@dataclass(frozen=True)
class EstimatorOutput:
    """What one input produced. kind: "initial" (the filter started at stamp_ns, at rest; ``estimate`` is
    None), "estimate" (a tick) or "repeat" (a repeated joint sample of the last tick; nothing ran). The
    joint arrays are the tick's joint state (None for a repeat)."""

    kind: str
    stamp_ns: int
    estimate: StateEstimate | None = None
    joints: JointArrays | None = None


class StreamingEstimator:
    """The estimator's tick logic over a stream of samples (constant memory); see the module docstring.

    Start pose: ``initial_position`` / ``initial_world_R_base`` or ``set_initial_pose`` (e.g. the first
    ground truth). Without a position the first tick stands the robot on flat ground at ``initial_xy``
    [m] (attitude ``initial_world_R_base``, level if None), unless ``wait_for_initial_pose``: then the first
    tick stays pending until a pose is set (and a restart forgets it). ``impedance`` and
    ``magnetic_field`` are the latest terrain impedance and magnetometer sample (IMU frame) a tick uses;
    with ``impedance_period_s`` > 0 the impedance is streamed with ``add_impedance`` and waited for (see the
    module docstring). ``on_reject(reason, message)`` and ``on_restart(stamp_ns)`` let a node log them.
    """

    def __init__(self, model: RobotModel, settings: StateEstimatorSettings | None = None, *,
                 magnetic_field_world: np.ndarray | None = None, initial_position: np.ndarray | None = None,
                 initial_world_R_base: np.ndarray | None = None, wait_for_initial_pose: bool = False,
                 initial_xy: tuple[float, float] = (0.0, 0.0), impedance_period_s: float = 0.0,
                 impedance_max_defer_s: float = 0.0,
                 on_reject: Callable[[str, str], None] | None = None,
                 on_restart: Callable[[int], None] | None = None) -> None:
        self.model = model
        self._magnetic_field_world = magnetic_field_world
        self.estimator = StateEstimator(model, settings, magnetic_field_world)
        self.period_ns = round(self.estimator.settings.period_s * 1e9)
        self.wait_for_initial_pose = wait_for_initial_pose
        self.initial_xy = initial_xy
        self.initial_world_R_base = initial_world_R_base
        self._initial_pose = None if initial_position is None else (initial_position, initial_world_R_base)
        self.on_reject = on_reject
        self.on_restart = on_restart
        self.impedance: LegImpedance | None = None
        for name, value in (("impedance_period_s", impedance_period_s),
                            ("impedance_max_defer_s", impedance_max_defer_s)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {value}")
        impedance_period_ns = round(impedance_period_s * 1e9)
        self._impedances = StampedInbox(impedance_period_ns, period_ns=impedance_period_ns) \
            if impedance_period_ns else None
        self.impedance_max_defer_ns = round(impedance_max_defer_s * 1e9)
        self.late_impedance_ticks = 0  # ticks run without the impedance they waited for
        self._waiting: list[_Pending] = []  # ticks whose samples are here, waiting for the impedance, in order
        self.magnetic_field: np.ndarray | None = None
        self.rejections: Counter[str] = Counter()
        self.ticks = 0
        self.restarts = 0
        self.duplicates = 0
        self.held_imu_ticks = 0
        self.nearest_imu_ticks = 0  # ticks whose IMU window was empty and that took the next sample
        self._last_imu_mean: tuple[np.ndarray, np.ndarray] | None = None
        self._next_tick_ns = 0
        self._last_tick_ns: int | None = None
        self._imu: list[tuple[int, np.ndarray, np.ndarray]] = []   # IMU samples after the last tick
        self._last_imu_ns: int | None = None
        self._rejected_imu_ns: int | None = None  # the last rejected IMU sample's stamp
        self._pending: _Pending | None = None  # the next tick: stamp, t, q, qd, tau, foot contact
        self._contacts: list[tuple[int, np.ndarray]] = []  # foot contact samples after the last tick
        self._last_contact_ns: int | None = None
        self._held_contact: np.ndarray | None = None
        self.deriving_velocities = False  # a joint state without velocities was seen: all samples are read
        self._velocity_filter = self._new_velocity_filter()

    @property
    def settings(self) -> StateEstimatorSettings:
        return self.estimator.settings

    @property
    def _tolerance_ns(self) -> int:
        return round(self.estimator.settings.tick_tolerance_s * 1e9)

    @property
    def _sensed_contacts(self) -> bool:
        return self.estimator.settings.leg_odometry.contact_source != "torque"

    def _new_velocity_filter(self) -> JointVelocityFilter:
        s = self.estimator.settings
        return JointVelocityFilter(s.joint_velocity_cutoff_hz, s.max_gap_periods * s.period_s)

    @property
    def has_initial_pose(self) -> bool:
        return self._initial_pose is not None

    def reconfigure(self, settings: StateEstimatorSettings) -> None:
        """New settings from the next tick (``StateEstimator.reconfigure``); restarts keep them."""
        self.estimator.reconfigure(settings)
        self._velocity_filter.cutoff_hz = settings.joint_velocity_cutoff_hz

    # -- inputs -----------------------------------------------------------------------------------------------
    def set_initial_pose(self, position: np.ndarray, world_R_base: np.ndarray) -> list[EstimatorOutput]:
        """The start pose (world frame), if none is set yet; releases a tick that waited for it."""
        if self._initial_pose is not None:
            return []
        self._initial_pose = (position, world_R_base)
        return self._try_tick()

    def add_imu(self, stamp_ns: int, specific_force: np.ndarray, angular_rate: np.ndarray) -> list[EstimatorOutput]:
        """One IMU sample: specific force [m/s^2] and angular rate [rad/s], IMU frame."""
        try:
            f, w = self.estimator.check_imu(specific_force, angular_rate)
        except EstimatorInputError as exc:
            self._reject(exc.reason, str(exc))
            self._rejected_imu_ns = stamp_ns
            return []
        if self._last_imu_ns is not None and stamp_ns == self._last_imu_ns:
            self.duplicates += 1
            return []
        if self._last_imu_ns is not None and stamp_ns < self._last_imu_ns:
            if stamp_ns + CLOCK_RESET_NS < self._last_imu_ns:
                self._restart(stamp_ns)
            else:
                self._reject("imu_out_of_order", f"imu stamp {stamp_ns * 1e-9:.6f} s is not after "
                             f"{self._last_imu_ns * 1e-9:.6f} s")
                return []
        self._last_imu_ns = stamp_ns
        self._imu.append((stamp_ns, f, w))
        return self._try_tick()

    def wants_joints(self, stamp_ns: int) -> bool:
        """Whether ``add_joints`` would do anything with a sample stamped ``stamp_ns`` (a restart, a repeat, a
        tick): a node may skip deserialising the others (``tal_core.ros.cdr.subscribe_stamped``)."""
        return (self._last_tick_ns is not None and stamp_ns + CLOCK_RESET_NS < self._last_tick_ns) \
            or stamp_ns == self._last_tick_ns or reaches_tick(stamp_ns, self._next_tick_ns, self._tolerance_ns) \
            or self.deriving_velocities

    def add_contacts(self, stamp_ns: int, values: np.ndarray) -> list[EstimatorOutput]:
        """One foot contact sample (4 values, LF, RF, LH, RH): forces (raw or [N]) or flags, as the leg
        odometry's contact_source reads them. Ignored with contact_source torque."""
        if not self._sensed_contacts:
            return []
        contact = np.asarray(values, dtype=float)
        if contact.shape != (NUM_LEGS,) or not np.all(np.isfinite(contact)):
            self._reject("contacts", f"foot contact sample needs {NUM_LEGS} finite values, got {values!r}")
            return []
        if self._last_contact_ns is not None and stamp_ns <= self._last_contact_ns:
            if stamp_ns == self._last_contact_ns:
                self.duplicates += 1
            elif stamp_ns + CLOCK_RESET_NS >= self._last_contact_ns:
                self._reject("contacts", f"foot contact stamp {stamp_ns * 1e-9:.6f} s is not after "
                             f"{self._last_contact_ns * 1e-9:.6f} s")
            else:  # a restarted clock: the joints or the IMU restart the estimator
                self._contacts = [(stamp_ns, contact)]
                self._last_contact_ns = stamp_ns
            return []
        self._last_contact_ns = stamp_ns
        self._contacts.append((stamp_ns, contact))
        return self._try_tick()

    def add_joints(self, stamp_ns: int, read: Callable[[], JointArrays], t_s: float | None = None,
                   foot_contact: np.ndarray | None = None) -> list[EstimatorOutput]:
        """One joint-state sample. ``read()`` gives its arrays (called only for a tick's sample, so a node
        converts only those messages, unless velocities are derived; InputError rejects the sample).
        ``t_s``: the time [s] the filter sees for it (default stamp_ns * 1e-9; an in-process runner on a
        float clock passes its own). ``foot_contact``: the feet's sensor values of this stamp, if the
        sample carries them (else ``add_contacts``)."""
        if self._last_tick_ns is not None and stamp_ns + CLOCK_RESET_NS < self._last_tick_ns:
            self._restart(stamp_ns)
        if stamp_ns == self._last_tick_ns:
            self.duplicates += 1
            return [EstimatorOutput("repeat", stamp_ns)]
        t = stamp_ns * 1e-9 if t_s is None else t_s
        if not reaches_tick(stamp_ns, self._next_tick_ns, self._tolerance_ns):
            if self.deriving_velocities:  # every sample feeds the velocity filter
                try:
                    self._velocity_filter.update(t, read()[0])
                except InputError as exc:
                    self._reject("joints", str(exc))
            return []
        try:
            q, qd, tau = read()
        except InputError as exc:
            self._reject("joints", str(exc))
            return []
        if qd is None:
            self.deriving_velocities = True
            qd = self._velocity_filter.update(t, q)
        elif self.deriving_velocities:
            self._velocity_filter.update(t, q)
        out = self._release_waiting(stamp_ns)
        if self._pending is not None and self._pending[0] < stamp_ns:
            out += self._wait_or_tick(self._pending)  # its IMU sample never came: run it with what arrived
        # The grid point is taken: later samples before the next one are not ticks, whether or not the
        # IMU sample of this one has arrived yet (topics are delivered in no fixed order).
        self._next_tick_ns = tick_after(stamp_ns, self.period_ns, self._tolerance_ns)
        contact = None if foot_contact is None else np.asarray(foot_contact, dtype=float)
        self._pending = (stamp_ns, t, q, qd, tau, contact)
        return out + self._try_tick()

    def add_impedance(self, stamp_ns: int, impedance: LegImpedance) -> list[EstimatorOutput]:
        """The TCE's answer to its tick at ``stamp_ns``; the waiting tick it completes, if any. Without an
        ``impedance_period_s`` it is simply the latest."""
        if self._impedances is None:
            self.impedance = impedance
            return []
        self._impedances.add(stamp_ns, impedance)
        return self._release_waiting(None) + self._try_tick()

    @property
    def impedance_repeats(self) -> int:
        """Streamed impedances dropped as repeats of a stamp already received (a re-sent answer)."""
        return 0 if self._impedances is None else self._impedances.repeats

    def _impedance_awaited(self, stamp_ns: int) -> bool:
        return self._impedances is not None and self._impedances.awaited(stamp_ns) is not None

    def _wait_or_tick(self, pending: _Pending) -> list[EstimatorOutput]:
        """A tick whose samples are complete: computed now, or queued while it (or an earlier one) waits for
        the impedance."""
        if self.estimator.initialised and (self._waiting or self._impedance_awaited(pending[0])):
            if self._pending is pending:
                self._pending = None
            self._waiting.append(pending)
            return self._release_waiting(None)
        return self._tick(pending)

    def _release_waiting(self, newest_ns: int | None) -> list[EstimatorOutput]:
        """The queued ticks that can run, in order: their impedance is here, or a joint sample stamped
        ``newest_ns`` is more than impedance_max_defer_s past them (late)."""
        out: list[EstimatorOutput] = []
        while self._waiting:
            stamp = self._waiting[0][0]
            if self._impedance_awaited(stamp):
                if newest_ns is None or newest_ns - stamp <= self.impedance_max_defer_ns:
                    break
                self.late_impedance_ticks += 1
            out += self._tick(self._waiting.pop(0))
        return out

    def add_sample(self, stamp_ns: int, specific_force: np.ndarray, angular_rate: np.ndarray,
                   joint_position: np.ndarray, joint_velocity: np.ndarray | None, joint_torque: np.ndarray | None,
                   t_s: float | None = None, foot_contact: np.ndarray | None = None) -> list[EstimatorOutput]:
        """The IMU and joint samples of one stamp (a simulator step, a row of recorded arrays), with the
        feet's sensor values of that stamp for a sensor contact source."""
        out = self.add_imu(stamp_ns, specific_force, angular_rate)
        return out + self.add_joints(stamp_ns, lambda: (joint_position, joint_velocity, joint_torque), t_s,
                                     foot_contact)

    # -- the tick ---------------------------------------------------------------------------------------------
    def _reject(self, reason: str, message: str) -> None:
        self.rejections[reason] += 1
        if self.on_reject is not None:
            self.on_reject(reason, message)

    def _restart(self, stamp_ns: int) -> None:
        self.restarts += 1
        if self.on_restart is not None:
            self.on_restart(stamp_ns)
        self.estimator = StateEstimator(self.model, self.estimator.settings, self._magnetic_field_world)
        self._next_tick_ns = 0
        self._last_tick_ns = None
        self._imu.clear()
        self._last_imu_ns = None
        self._rejected_imu_ns = None
        self._pending = None
        self._contacts.clear()
        self._last_contact_ns = None
        self._held_contact = None
        self._waiting.clear()
        if self._impedances is not None:  # a streamed impedance belongs to the old clock
            self._impedances.clear()
            self.impedance = None
        self._velocity_filter.reset()
        if self.wait_for_initial_pose:
            self._initial_pose = None

    def _try_tick(self) -> list[EstimatorOutput]:
        if self._pending is None or self._last_imu_ns is None or self._last_imu_ns < self._pending[0]:
            return []
        if self._sensed_contacts and self._pending[5] is None and (
                self._last_contact_ns is None or self._last_contact_ns < self._pending[0]):
            return []  # the foot contact sample of this stamp may still come
        return self._wait_or_tick(self._pending)

    def _tick_contact(self, stamp: int, given: np.ndarray | None) -> np.ndarray | None:
        """The foot contact values of the tick at ``stamp``: those given with its joint sample, else the
        latest sample at or before it (held from an earlier tick if none came since)."""
        if not self._sensed_contacts:
            return None
        window = [c for c in self._contacts if c[0] <= stamp]
        self._contacts = [c for c in self._contacts if c[0] > stamp]
        if given is not None:
            self._held_contact = given
        elif window:
            self._held_contact = window[-1][1]
        return self._held_contact

    def _tick(self, pending: _Pending) -> list[EstimatorOutput]:
        stamp, t_s, q, qd, tau, given_contact = pending
        est = self.estimator
        if not est.initialised:
            if self.wait_for_initial_pose and self._initial_pose is None:
                return []  # the tick stays pending until the pose comes
            self._pending = None
            self._imu = [s for s in self._imu if s[0] > stamp]
            if self._initial_pose is not None:
                est.initialise(t_s, *self._initial_pose)
            else:
                est.initialise_standing(t_s, q, self.initial_xy, world_R_base=self.initial_world_R_base)
            self._last_tick_ns = stamp
            self._tick_contact(stamp, given_contact)
            return [EstimatorOutput("initial", stamp, None, (q, qd, tau))]
        if self._pending is pending:
            self._pending = None
        samples = [s for s in self._imu if s[0] <= stamp]
        self._imu = [s for s in self._imu if s[0] > stamp]
        rejected_in_window = (self._rejected_imu_ns is not None and self._last_tick_ns is not None
                              and self._last_tick_ns < self._rejected_imu_ns <= stamp)
        if not samples and not rejected_in_window and self._imu and self._imu[0][0] < stamp + self.period_ns:
            # IMU stamps with a jitter of their own: none fell in (previous tick, tick], the one that released
            # the tick is the nearest; it is this tick's, not the next one's.
            samples = [self._imu.pop(0)]
            self.nearest_imu_ticks += 1
        if samples:
            f = np.mean([s[1] for s in samples], axis=0)
            w = np.mean([s[2] for s in samples], axis=0)
            self._last_imu_mean = (f, w)
        elif self._last_imu_mean is not None:
            self.held_imu_ticks += 1  # every sample of the interval was rejected: hold the last mean
            f, w = self._last_imu_mean
        else:
            self._reject("no_imu", f"no IMU sample for the tick at {stamp * 1e-9:.6f} s")
            return []
        if self._impedances is not None:
            due = self._impedances.due(stamp)
            if due:
                self.impedance = due[-1][1]
        contact = self._tick_contact(stamp, given_contact)
        if self._sensed_contacts and contact is None:
            self._reject("no_contacts", f"no foot contact sample for the tick at {stamp * 1e-9:.6f} s")
            return []
        try:
            estimate = est.update(t_s, f, w, q, qd, tau, impedance=self.impedance, magnetic_field=self.magnetic_field,
                                  foot_contact=contact)
        except EstimatorInputError as exc:
            self._reject(exc.reason, str(exc))
            return []
        self._last_tick_ns = stamp
        self.ticks += 1
        return [EstimatorOutput("estimate", stamp, estimate, (q, qd, tau))]
