"""The bridge's timing, ROS-free: which outputs are due at a physics step, the lockstep protocol (which control
tick the simulation waits for, when a command releases it, when a silent controller is stepped past) and the
real-time pacing (how many physics steps the wall clock asks for, dropping a backlog rather than spiralling).

The ``sim_bridge`` node and the offline dataset recorder (``tal_lab.datasets``) share it, so a bag made offline
has the same message schedule as a live run. Times: integer nanoseconds for sim time, float seconds for the
monotonic wall clock (``time.monotonic()``).
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import BridgeConfigError


@dataclass(frozen=True)
class DueOutputs:
    """What to publish after one physics step."""

    clock: bool  # clock
    sensors: bool  # joint_states, imu
    contacts: bool  # ground_truth/contacts
    heightmap: bool  # terrain/heightmap
    ground_truth: bool  # ground_truth/odom


@dataclass(frozen=True)
class OutputSchedule:
    """Every output as a whole number of physics steps. Ground truth (evaluation, and the base state of a
    controller run on it) comes at the control rate by default: a motion-capture rate, and every control tick
    finds the base state of its own stamp."""

    sensor_every: int = 1
    contact_every: int = 4
    heightmap_every: int = 50
    clock_every: int = 1
    ground_truth_every: int = 1

    def __post_init__(self) -> None:
        for name in ("sensor_every", "contact_every", "heightmap_every", "clock_every", "ground_truth_every"):
            if int(getattr(self, name)) < 1:
                raise BridgeConfigError(f"OutputSchedule.{name} must be >= 1 step, got {getattr(self, name)}")

    @classmethod
    def from_rates(cls, physics_rate_hz: float, sensor_rate_hz: float, contact_rate_hz: float,
                   heightmap_rate_hz: float, clock_rate_hz: float | None = None,
                   ground_truth_rate_hz: float | None = None) -> OutputSchedule:
        """Rates [Hz] rounded to whole physics steps (at least one); the clock at every step and ground truth
        with the sensors by default."""
        if physics_rate_hz <= 0.0:
            raise BridgeConfigError(f"physics_rate_hz must be > 0, got {physics_rate_hz}")
        rates = (sensor_rate_hz, contact_rate_hz, heightmap_rate_hz, clock_rate_hz or physics_rate_hz,
                 ground_truth_rate_hz or sensor_rate_hz)
        return cls(*(max(1, round(physics_rate_hz / rate)) for rate in rates))

    def check_control_steps(self, steps_per_control: int) -> None:
        """BridgeConfigError unless every control tick has a ground-truth sample of its own stamp (a
        controller or estimator run on ground truth waits for the base state of its tick)."""
        if int(steps_per_control) % self.ground_truth_every != 0:
            raise BridgeConfigError(
                f"ground truth every {self.ground_truth_every} physics steps does not fall on every control tick "
                f"({steps_per_control} steps): set ground_truth_rate_hz to a whole multiple of the control rate")

    def due(self, step: int, force_all: bool = False) -> DueOutputs:
        return DueOutputs(force_all or step % self.clock_every == 0, force_all or step % self.sensor_every == 0,
                          force_all or step % self.contact_every == 0, force_all or step % self.heightmap_every == 0,
                          force_all or step % self.ground_truth_every == 0)


class LockstepGate:
    """Lockstep: the simulation stands at a control tick until a command stamped at (or after) it arrives; a
    controller silent for ``timeout_s`` of wall time (``startup_timeout_s`` before its first command: DDS
    discovery) is stepped past with the held command and counted."""

    def __init__(self, timeout_s: float, startup_timeout_s: float) -> None:
        self.timeout_s = float(timeout_s)
        self.startup_timeout_s = float(startup_timeout_s)
        self.awaiting_tick_ns: int | None = None
        self.waiting_since_s = 0.0
        self.timeouts = 0

    def wait_for(self, tick_ns: int, now_s: float) -> None:
        """The simulation now stands at ``tick_ns`` and waits for its command."""
        self.awaiting_tick_ns = int(tick_ns)
        self.waiting_since_s = float(now_s)

    def release(self) -> None:
        """The simulation advances (a command arrived or the wait timed out)."""
        self.awaiting_tick_ns = None

    def releases(self, command_stamp_ns: int) -> bool:
        """Whether a command stamped ``command_stamp_ns`` is the one the waiting tick needs."""
        return self.awaiting_tick_ns is not None and int(command_stamp_ns) >= self.awaiting_tick_ns

    def timed_out(self, now_s: float, commands_accepted: int) -> float | None:
        """The timeout [s] that expired while waiting (counted), or None."""
        if self.awaiting_tick_ns is None:
            return None
        timeout = self.startup_timeout_s if commands_accepted == 0 else self.timeout_s
        if now_s - self.waiting_since_s > timeout:
            self.timeouts += 1
            return timeout
        return None


class RealtimePacer:
    """Real time: physics follows the wall clock from ``start_s``; at most ``max_catch_up_steps`` per call, a
    larger backlog is dropped (counted as an overrun) and sim time then runs slower than the wall clock."""

    def __init__(self, physics_rate_hz: float, max_catch_up_steps: int, start_s: float) -> None:
        if physics_rate_hz <= 0.0 or max_catch_up_steps < 1:
            raise BridgeConfigError(f"RealtimePacer needs physics_rate_hz > 0 and max_catch_up_steps >= 1, got "
                                    f"{physics_rate_hz} and {max_catch_up_steps}")
        self.physics_rate_hz = float(physics_rate_hz)
        self.max_catch_up_steps = int(max_catch_up_steps)
        self.start_s = float(start_s)
        self.overruns = 0

    def steps_due(self, now_s: float, step_count: int) -> int:
        """Physics steps to take now so that the simulation is at the wall clock (capped)."""
        behind = int((now_s - self.start_s) * self.physics_rate_hz) - int(step_count)
        if behind > self.max_catch_up_steps:
            self.overruns += 1
            self.start_s += (behind - self.max_catch_up_steps) / self.physics_rate_hz
            behind = self.max_catch_up_steps
        return max(0, behind)
