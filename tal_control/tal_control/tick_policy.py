"""The wbc's tick policy (no rclpy): when a control tick is due, which inputs it uses, restarts, safe mode
and the watchdog. The ``wbc`` node feeds it every arrival and acts on its answers; an offline runner can
feed it the same stamps and get the same decisions.

Stamps are integer nanoseconds of sim time. Ticks lie on the grid k * period_ns (``tal_core.ticks``).

- A tick is due when a joint state reaches the next grid point. It is computed once the base state
  expected for it has arrived (ground truth: the same stamp; an estimate published every
  ``base_period_ns``: the estimator's latest tick at or before it) and, with ``contacts``, the foot
  contacts of its stamp (with ``contact_period_ns``, as the estimator's contact estimate: its latest tick at
  or before the stamp). Arrival order does not matter, so lockstep runs are deterministic. A tick whose
  inputs have not arrived is deferred; it is decided, with whatever base state is there, when a later
  joint state arrives (the robot driver moved on).
- A tick whose base state is older than ``stale_periods`` control periods is a safe-mode tick (joint
  damping hold); the first normal tick after it leaves safe mode.
- A heightmap comes into use at the first tick at least one control period after its stamp (one stamped
  with the tick itself may arrive before or after the tick's joint state). With ``heightmap_period_ns`` (the
  bridge publishes its map on that sim-time grid) a tick also waits for the map due at it: DDS gives no order
  between topics, and a large map can arrive after the next tick's joint state even in lockstep. Maps that
  came after the tick that should have used them are counted (``late_heightmaps``).
- Inputs computed from an earlier tick (``lagged``: terrain impedance, footholds, body pose references,
  stamped with the tick they answer) are held and handed to the first tick at least one control period
  after their stamp, in stamp order. A tick also waits for the answer to the previous tick of every input
  named in ``waited_inputs`` (a newer one will do: the producer skipped a tick), so what it uses does not
  depend on how fast the producer was. A producer that answers only every ``P`` of sim time
  (``waited_periods_ns``: the first tick at least ``P`` after its last answer, as the VPA) is waited for
  when such a tick lies at least one period back. The first tick waits (wall time, up to
  ``command_source_wait_s``, like the wait for a command source) for a first answer of each input that does
  not answer the wbc's own gait state, and for ``producers_ready()`` (the others' subscriptions discovered):
  a producer discovered late would otherwise miss the first ticks, and every later tick would wait for
  answers that never come. An input not ready by then is no longer waited for (``unanswered_inputs``).
- A joint state more than ``CLOCK_RESET_NS`` older than the last one is a restarted clock: every input is
  forgotten and the grid starts again (the node starts its controller afresh). Base states and contacts
  that jump back likewise replace the held ones.
- The driver repeats the state it last got an answer for (a command sent before DDS matched): the policy
  says so, and the node sends the same command again. Likewise a producer may send its answer again (the
  node re-sends a gait state whose answers are overdue: DDS may drop what is published before a late
  subscriber matched); a lagged input with the stamp of the newest one is a repeat and is dropped.
- ``command_source_wait_s``: the first tick waits (wall time) until a command source exists.
- The watchdog (``watchdog_timeout_s`` of steady time after the last joint state was handled) trips into
  safe mode while the driver is silent.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import Enum
from typing import Any

import numpy as np

from tal_core.errors import InputError
from tal_core.ticks import CLOCK_RESET_NS, TICK_TOLERANCE_NS, StampedInbox, reaches_tick, tick_after

from .velocity_command import VelocityCommandInput


class Mode(Enum):
    """What the last command was: the QP's solution, its fallback, or the safe-mode damping hold."""

    NORMAL = "normal"
    FALLBACK = "fallback"
    SAFE = "safe"


@dataclass(frozen=True)
class TickPolicyConfig:
    """period_ns: control tick [ns]. stale_periods: a base state older than this many periods means safe
    mode. base_period_ns: the base state's publishing period [ns] (None: one with every joint state, as
    ground truth). contacts: a tick also waits for the foot contacts of its stamp. contact_period_ns: the
    contacts' publishing period [ns] (None: with every joint state, as contact sensors; the estimator's
    contact estimate: its tick period). command_source_wait_s
    [s] (wall time): the first tick waits this long for a command source (0: no wait).
    watchdog_timeout_s [s] (steady time): silence of the driver before safe mode (0: off).
    max_defer_ns: a tick deferred for its base state (or contacts) runs anyway on the first joint sample more
    than this past it (0: the next sample, which in lockstep only comes after a lockstep timeout; on the wall
    clock the next sample comes 1 ms later, before the estimator's answer, so real-time runs wait longer).
    waited_inputs: lagged inputs (``WbcTickPolicy.lagged``) a tick waits for, the previous tick's answer.
    waited_periods_ns: (name, P) of waited inputs answered every P [ns] of sim time (default: every tick).
    gait_driven: waited inputs computed from the wbc's gait_state (no first answer before the first tick).
    startup_inputs: inputs only the first tick waits for (up to command_source_wait_s: a first answer, or for
    gait-driven ones their producers' discovery), where later ticks do not wait (on the wall clock: the robot
    starts once the nodes it listens to run; eight processes starting on two cores took 10-15 s, and a wbc
    that started walking before them fell at 2-3 s, starved while they loaded).
    heightmap_period_ns: the heightmap's publishing period [ns] on the sim-time grid: a tick waits for the map
    due at it (0: maps are used as they arrive)."""

    period_ns: int
    stale_periods: int = 3
    base_period_ns: int | None = None
    contacts: bool = False
    contact_period_ns: int | None = None
    command_source_wait_s: float = 0.0
    watchdog_timeout_s: float = 0.0
    max_defer_ns: int = 0
    waited_inputs: tuple[str, ...] = ()
    waited_periods_ns: tuple[tuple[str, int], ...] = ()
    gait_driven: tuple[str, ...] = ()
    startup_inputs: tuple[str, ...] = ()
    heightmap_period_ns: int = 0

    def __post_init__(self) -> None:
        if self.period_ns <= 0:
            raise InputError(f"tick policy: period_ns must be > 0, got {self.period_ns!r}")
        if self.stale_periods < 1:
            raise InputError(f"tick policy: stale_periods must be >= 1, got {self.stale_periods!r}")
        if self.max_defer_ns < 0:
            raise InputError(f"tick policy: max_defer_ns must be >= 0, got {self.max_defer_ns!r}")
        if self.heightmap_period_ns < 0:
            raise InputError(f"tick policy: heightmap_period_ns must be >= 0, got {self.heightmap_period_ns!r}")
        if self.base_period_ns is not None and self.base_period_ns <= 0:
            raise InputError(f"tick policy: base_period_ns must be > 0 or None, got {self.base_period_ns!r}")
        for name in ("command_source_wait_s", "watchdog_timeout_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"tick policy: {name} must be finite and >= 0, got {value!r}")


@dataclass(frozen=True)
class Stamped:
    """An input sample (whatever the caller stores: arrays, a message, a map) with its stamp [ns]."""

    stamp_ns: int
    value: Any


@dataclass(frozen=True)
class Tick:
    """A decided tick. safe_reason set: a safe-mode tick (stale base state), otherwise a normal one.
    joints, base: the samples it uses; base_age_ns: stamp - base stamp. heightmap: the map in use (None:
    none yet). contacts: the contacts of its stamp (None: not used or none fresh: the gait plan).
    command: the velocity command in force (vx, vy [m/s], yaw rate [rad/s])."""

    stamp_ns: int
    joints: Any
    base: Any
    base_age_ns: int
    command: np.ndarray
    heightmap: Any = None
    contacts: Any = None
    safe_reason: str | None = None
    inputs: tuple[tuple[str, Any], ...] = ()  # lagged inputs released to this tick: (name, value), stamp order


@dataclass(frozen=True)
class Arrival:
    """What the caller does after an input arrived. tick: compute it (None: nothing due). restarted: the
    clock jumped back, start the controller afresh (before computing ``tick``). repeat_answer: the driver
    repeats the state last answered, send the same command again. feed_watchdog: once the tick (if any)
    is done, call ``feed_watchdog``. command_source_missing: the wait for a command source ended without
    one (say so once)."""

    tick: Tick | None = None
    restarted: bool = False
    repeat_answer: bool = False
    feed_watchdog: bool = False
    command_source_missing: bool = False


@dataclass(frozen=True)
class WatchdogTrip:
    """The watchdog fired: send a safe-mode command stamped ``stamp_ns`` (the last joint state's);
    silence_s [s]: steady time since the last joint state was handled."""

    stamp_ns: int
    silence_s: float


def _accepts(held: Stamped | None, stamp_ns: int) -> bool:
    """A sample stamped ``stamp_ns`` replaces ``held`` when newer, or when ``held`` is from before a
    restarted clock; an older or repeated one is dropped."""
    return held is None or stamp_ns > held.stamp_ns or stamp_ns + CLOCK_RESET_NS < held.stamp_ns


@dataclass
class _Counters:
    ticks: int = 0                   # normal ticks computed
    repeated_answers: int = 0        # lagged inputs received again with the newest stamp (dropped)
    deferred_ticks: int = 0          # ticks whose base state (or contacts) had not arrived with their joint state
    ticks_without_waited: int = 0    # ticks run (past max_defer) without the previous tick's waited input
    ticks_without_heightmap: int = 0  # ticks run (past max_defer) without the heightmap due at them
    ticks_without_contacts: int = 0  # contacts expected, none fresh for the tick (the plan used)
    watchdog_trips: int = 0          # safe-mode commands asked for by the watchdog
    command_source_waits: int = 0    # ticks held back waiting for a command source
    restarts: int = 0                # clock jumps back


class WbcTickPolicy:
    """The wbc's timing state machine (see the module docstring). Feed it ``joint_state``,
    ``base_state``, ``contacts``, ``heightmap`` and velocity commands (``commands``); tell it
    ``answered`` for every command sent, ``tick_done`` / ``enter_safe_mode`` for what a tick became,
    ``feed_watchdog`` after handling a joint state, and ask ``watchdog`` when its timer fires.

    clock: steady time [s] (watchdog, command source wait). command_source_found: whether a command
    source exists (asked only while the first tick waits for one).
    """

    def __init__(self, config: TickPolicyConfig, commands: VelocityCommandInput | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 command_source_found: Callable[[], bool] = lambda: True,
                 producers_ready: Callable[[], bool] = lambda: True) -> None:
        self.config = config
        self.producers_ready = producers_ready
        self.commands = commands if commands is not None else VelocityCommandInput(math.inf, math.inf)
        self.clock = clock
        self.command_source_found = command_source_found
        self.counters = _Counters()
        self.mode = Mode.NORMAL
        self.next_tick_ns = 0
        self._joints: Stamped | None = None
        self._base: Stamped | None = None
        self._contacts: Stamped | None = None
        self._deferred_tick_ns: int | None = None
        self._answered_ns: int | None = None
        self._heightmap: Any = None
        self._heightmaps = StampedInbox(config.period_ns, period_ns=config.heightmap_period_ns)  # not yet in use
        self._lagged: list[tuple[int, str, Any]] = []  # (stamp, name, value): received, not yet released
        self._newest_lagged: dict[str, int] = {}
        self._fed_s: float | None = None
        self._source_deadline_s = (None if config.command_source_wait_s <= 0.0
                                   else clock() + config.command_source_wait_s)
        # What the first tick waits for: the waited inputs and the startup-only ones.
        self._first_waited = tuple(dict.fromkeys((*config.waited_inputs, *config.startup_inputs)))
        self._inputs_deadline_s = (None if config.command_source_wait_s <= 0.0 or not self._first_waited
                                   else clock() + config.command_source_wait_s)
        self._waited = tuple(config.waited_inputs)
        self.unanswered_inputs: tuple[str, ...] = ()  # waited inputs that gave no first answer in time
        self.deferred_for: tuple[str, ...] = ()  # what the deferred tick lacks (diagnostics)

    # -- configuration -------------------------------------------------------------------------------------
    @property
    def stale_ns(self) -> int:
        """[ns] base states older than this at a tick mean safe mode."""
        return self.config.stale_periods * self.config.period_ns

    def set_stale_periods(self, periods: int) -> None:
        """Change ``stale_periods`` (from the next tick on); InputError below 1."""
        self.config = replace(self.config, stale_periods=int(periods))

    @property
    def waiting_for_command_source(self) -> bool:
        return self._source_deadline_s is not None

    @property
    def heightmap_in_use(self) -> Any:
        return self._heightmap

    @property
    def waiting_for_answers(self) -> bool:
        """Whether the deferred tick waits for a waited input's answer (the node may re-send its gait state)."""
        return self._deferred_tick_ns is not None and "waited inputs" in self.deferred_for

    @property
    def late_heightmaps(self) -> int:
        """Maps that arrived after the tick that should have used them."""
        return self._heightmaps.late

    @property
    def missed_heightmaps(self) -> int:
        """Maps due at a tick that never came while a newer one did (``StampedInbox.missed``)."""
        return self._heightmaps.missed

    def first_tick_waits_for(self) -> tuple[str, ...]:
        """What the first tick still waits for (empty once it is computed, or when nothing is missing), for a
        node to say why a lockstep run does not start."""
        if self.next_tick_ns > 0:  # the first tick has been decided
            return ()
        out = [what for what, missing in (("a joint state", self._joints is None), ("a base state", self._base is None))
               if missing]
        if self._source_deadline_s is not None and not self.command_source_found():
            out.append("a cmd_vel_stamped publisher")
        if self._inputs_deadline_s is not None:
            gait_driven = self.config.gait_driven
            out += [f"the first {name} answer" for name in self._first_waited
                    if name not in gait_driven and name not in self._newest_lagged]
            if any(name in gait_driven for name in self._first_waited) and not self.producers_ready():
                out.append("the footholds / body pose producers' gait_state subscriptions")
        out += [f"its {what}" for what in self.deferred_for if what != "waited inputs"]
        return tuple(out)

    # -- arrivals ------------------------------------------------------------------------------------------
    def wants_joint_state(self, stamp_ns: int) -> bool:
        """Whether ``joint_state`` would act on a sample stamped ``stamp_ns`` beyond keeping it as the newest: a
        restart, a repeat to answer, the first sample, a control tick, a deferred tick or the wait for a command
        source. A node may skip deserialising the others (``tal_core.ros.cdr.subscribe_stamped``): a skipped
        sample would only have replaced the newest one, which no decision reads before the next tick."""
        last = self._joints
        deferred = self._deferred_tick_ns
        waiting = deferred is not None and deferred < stamp_ns <= deferred + self.config.max_defer_ns
        return (last is None or stamp_ns + CLOCK_RESET_NS < last.stamp_ns or stamp_ns == self._answered_ns
                or (reaches_tick(stamp_ns, self.next_tick_ns) and not waiting)
                or (deferred is not None and not waiting) or self._source_deadline_s is not None
                or self._inputs_deadline_s is not None)

    def joint_state(self, stamp_ns: int, sample: Any) -> Arrival:
        """A valid joint state stamped ``stamp_ns``: restart, repeat, drop, or store it and decide the tick."""
        restarted = self._joints is not None and stamp_ns + CLOCK_RESET_NS < self._joints.stamp_ns
        if restarted:
            self._restart(stamp_ns)
        if self._answered_ns is not None and stamp_ns == self._answered_ns:
            return Arrival(restarted=restarted, repeat_answer=True)
        deferred, max_defer = self._deferred_tick_ns, self.config.max_defer_ns
        if max_defer and deferred is not None and deferred < stamp_ns <= deferred + max_defer:
            return Arrival(restarted=restarted, feed_watchdog=True)  # the deferred tick keeps its sample, waiting
        if self._joints is not None and stamp_ns <= self._joints.stamp_ns:
            if stamp_ns == self._joints.stamp_ns and (self.waiting_for_command_source
                                                      or self._inputs_deadline_s is not None):
                # The driver repeats its first state while we wait for the command source: try again.
                tick, missing = self._decide()
                return Arrival(tick=tick, command_source_missing=missing)
            return Arrival(restarted=restarted)  # repeated or out-of-order sample: keep the newer one
        self._joints = Stamped(stamp_ns, sample)
        tick, missing = self._decide()
        return Arrival(tick=tick, restarted=restarted, feed_watchdog=True, command_source_missing=missing)

    def base_state(self, stamp_ns: int, sample: Any) -> Arrival:
        """A valid base state: kept when newer (or after a restarted clock); it may complete a deferred tick."""
        if not _accepts(self._base, stamp_ns):
            return Arrival()
        self._base = Stamped(stamp_ns, sample)
        return self._decided()

    def contacts(self, stamp_ns: int, sample: Any) -> Arrival:
        """Foot contacts: kept when newer (or after a restarted clock); they may complete a deferred tick."""
        if not _accepts(self._contacts, stamp_ns):
            return Arrival()
        self._contacts = Stamped(stamp_ns, sample)
        return self._decided()

    def lagged(self, name: str, stamp_ns: int, value: Any) -> Arrival:
        """An input computed for the tick ``stamp_ns`` (see the module docstring): held until the first tick one
        control period later; a waited one may complete a deferred tick."""
        newest = self._newest_lagged.get(name)
        if newest is not None and stamp_ns + CLOCK_RESET_NS < newest:
            self._lagged = [item for item in self._lagged if item[1] != name]  # the producer restarted
            newest = None
        if newest is not None and int(stamp_ns) == newest:
            self.counters.repeated_answers += 1  # a producer re-sent its answer (resend_gait_state): have it once
            return Arrival()
        self._lagged.append((int(stamp_ns), name, value))
        self._newest_lagged[name] = int(stamp_ns) if newest is None else max(newest, int(stamp_ns))
        if name in self._waited:
            return self._decided()
        return Arrival()

    def heightmap(self, stamp_ns: int, heightmap: Any) -> Arrival:
        """A valid heightmap; it comes into use at the first tick one control period after its stamp, and may
        complete a tick that waits for it."""
        self._heightmaps.add(stamp_ns, heightmap)
        if self.config.heightmap_period_ns and self._deferred_tick_ns is not None:
            return self._decided()
        return Arrival()

    def answered(self, stamp_ns: int) -> None:
        """A command stamped ``stamp_ns`` was sent (the driver may repeat that state until it gets it)."""
        self._answered_ns = stamp_ns

    # -- what a tick became --------------------------------------------------------------------------------
    def tick_done(self, fallback: bool) -> bool:
        """A normal tick was computed (``fallback``: by the QP's fallback); returns whether it left safe mode."""
        left = self.mode is Mode.SAFE
        self.mode = Mode.FALLBACK if fallback else Mode.NORMAL
        self.counters.ticks += 1
        return left

    def enter_safe_mode(self) -> bool:
        """A safe-mode command is sent (stale state, bad state, watchdog); returns whether it entered safe mode."""
        entered = self.mode is not Mode.SAFE
        self.mode = Mode.SAFE
        return entered

    # -- watchdog ------------------------------------------------------------------------------------------
    def feed_watchdog(self) -> None:
        """A joint state was handled (and maybe its tick computed): the silence counts from now."""
        self._fed_s = self.clock()

    def watchdog(self) -> WatchdogTrip | None:
        """The watchdog's check (its timer fired): a trip when the driver has been silent for at least
        ``watchdog_timeout_s`` since the last joint state was handled; None otherwise (or off, or no joint
        state yet)."""
        timeout = self.config.watchdog_timeout_s
        if timeout <= 0.0 or self._joints is None or self._fed_s is None:
            return None
        silence_s = self.clock() - self._fed_s
        if silence_s < timeout:
            return None
        self.counters.watchdog_trips += 1
        return WatchdogTrip(self._joints.stamp_ns, silence_s)

    # -- the decision --------------------------------------------------------------------------------------
    def expected_base_stamp(self, stamp_ns: int) -> int:
        """The stamp of the newest base state the source publishes at or before ``stamp_ns``: ground truth
        comes with every physics step, an estimate on its own tick grid."""
        return self._latest_on_grid(stamp_ns, self.config.base_period_ns)

    def expected_contacts_stamp(self, stamp_ns: int) -> int:
        """The stamp of the newest foot contacts the source publishes at or before ``stamp_ns``."""
        return self._latest_on_grid(stamp_ns, self.config.contact_period_ns)

    @staticmethod
    def _latest_on_grid(stamp_ns: int, period: int | None) -> int:
        if period is None:
            return stamp_ns
        return ((stamp_ns + TICK_TOLERANCE_NS) // period) * period

    def _decided(self) -> Arrival:
        tick, missing = self._decide()
        return Arrival(tick=tick, feed_watchdog=tick is not None, command_source_missing=missing)

    def _decide(self) -> tuple[Tick | None, bool]:
        """The tick due now, if its inputs are there (see the module docstring); and whether the wait for
        a command source just ended without one."""
        if self._joints is None or self._base is None:
            return None, False
        awaiting, missing = self._awaiting_command_source()
        if awaiting:
            return None, False
        stamp = self._joints.stamp_ns
        if not reaches_tick(stamp, self.next_tick_ns):
            return None, missing  # not a control tick
        base_stamp = self._base.stamp_ns
        deferred_before = (self._deferred_tick_ns is not None
                           and stamp > self._deferred_tick_ns + self.config.max_defer_ns)
        contacts_missing = self.config.contacts and (
            self._contacts is None
            or self._contacts.stamp_ns < self.expected_contacts_stamp(stamp) - TICK_TOLERANCE_NS)
        waited_missing = self._waited_missing(stamp)
        map_missing = self._heightmaps.awaited(stamp) is not None
        base_missing = base_stamp < self.expected_base_stamp(stamp) - TICK_TOLERANCE_NS
        if (base_missing or contacts_missing or waited_missing or map_missing) and not deferred_before:
            self.deferred_for = tuple(name for name, missing in (
                ("base state", base_missing), ("contacts", contacts_missing),
                ("waited inputs", waited_missing), ("heightmap", map_missing)) if missing)
            if self._deferred_tick_ns is None:
                self._deferred_tick_ns = stamp
            self.counters.deferred_ticks += 1
            return None, missing
        self._deferred_tick_ns = None
        self.deferred_for = ()
        if waited_missing:
            self.counters.ticks_without_waited += 1
        if map_missing:
            self.counters.ticks_without_heightmap += 1
        self.next_tick_ns = tick_after(stamp, self.config.period_ns)
        command = self.commands.at_tick(stamp)
        self._update_heightmap(stamp)
        age = stamp - base_stamp
        tick = Tick(stamp, self._joints.value, self._base.value, age, command, heightmap=self._heightmap,
                    inputs=self._release_lagged(stamp))
        if age > self.stale_ns:
            return replace(tick, safe_reason=f"base state is {age * 1e-6:.1f} ms old"), missing
        return replace(tick, contacts=self._contacts_for(stamp)), missing

    def _awaiting_command_source(self) -> tuple[bool, bool]:
        """(whether the first tick still waits for a command source, whether that wait just ran out)."""
        if self._source_deadline_s is None:
            return False, False
        found = self.command_source_found()
        if found or self.clock() > self._source_deadline_s:
            self._source_deadline_s = None
            return False, not found
        self.counters.command_source_waits += 1
        return True, False

    def _contacts_for(self, stamp_ns: int) -> Any:
        if not self.config.contacts:
            return None
        if self._contacts is None or stamp_ns - self._contacts.stamp_ns > self.stale_ns:
            self.counters.ticks_without_contacts += 1
            return None
        return self._contacts.value

    def _waited_missing(self, stamp_ns: int) -> bool:
        """Whether a waited input has not yet answered the tick one period before ``stamp_ns``."""
        newest = self._newest_lagged
        gait_driven = self.config.gait_driven
        if self._inputs_deadline_s is not None:  # the first tick: first answers and producers, or the deadline
            first = self._first_waited
            answered = all(name in newest for name in first if name not in gait_driven)
            ready = not any(name in gait_driven for name in first) or self.producers_ready()
            if answered and ready:
                self._inputs_deadline_s = None
            elif self.clock() > self._inputs_deadline_s:
                self._inputs_deadline_s = None
                lost = tuple(name for name in first
                             if (name in gait_driven and not ready) or (name not in gait_driven and name not in newest))
                self.unanswered_inputs = lost
                self._waited = tuple(name for name in self._waited if name not in lost)
            return self._inputs_deadline_s is not None
        previous = stamp_ns - self.config.period_ns
        if previous < -TICK_TOLERANCE_NS:
            return False  # the first tick: there is no earlier one to answer
        periods = dict(self.config.waited_periods_ns)
        return any(name not in newest
                   or newest[name] + periods.get(name, self.config.period_ns) <= previous + TICK_TOLERANCE_NS
                   for name in self._waited)

    def _release_lagged(self, stamp_ns: int) -> tuple[tuple[str, Any], ...]:
        """The held inputs stamped at least one period before the tick, in (stamp, name) order."""
        cutoff = stamp_ns - self.config.period_ns + TICK_TOLERANCE_NS
        due = sorted((item for item in self._lagged if item[0] <= cutoff), key=lambda item: (item[0], item[1]))
        if not due:
            return ()
        self._lagged = [item for item in self._lagged if item[0] > cutoff]
        return tuple((name, value) for _, name, value in due)

    def _update_heightmap(self, stamp_ns: int) -> None:
        """The newest heightmap stamped at least one control period before the tick comes into use.

        A map stamped with the tick itself (or just before it) may arrive before or after the tick's joint
        state (another topic, no order between them), so using it at once made lockstep runs depend on
        delivery order. The maps of earlier ticks usually have been delivered by the time the next tick's
        joint state comes, but not always (a CI machine showed otherwise): with ``heightmap_period_ns`` the
        tick waits for its map (``_decide``).
        """
        due = self._heightmaps.due(stamp_ns)
        if due:
            self._heightmap = due[-1][1]

    def _restart(self, stamp_ns: int) -> None:
        """The clock jumped back to ``stamp_ns`` (simulation restarted): forget the inputs and the grid (the
        heightmap in use stays: the terrain did not move)."""
        self.counters.restarts += 1
        self._joints = self._base = None
        if self._contacts is not None and self._contacts.stamp_ns > stamp_ns:
            self._contacts = None
        self.next_tick_ns = 0
        self._deferred_tick_ns = None
        self._answered_ns = None
        self.commands.reset()
        self._heightmaps.clear()
        self._lagged = [item for item in self._lagged if item[0] <= stamp_ns]
        self._newest_lagged = {name: stamp for name, stamp in self._newest_lagged.items() if stamp <= stamp_ns}

