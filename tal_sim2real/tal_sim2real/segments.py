"""Open-loop prediction segments: the simulator started from a measured state and driven by the measured
joint torques for a short horizon, compared with what was measured next.

Short segments keep simulation and measurement from drifting apart (a closed-loop re-run diverges after
the first different footstep), and the measured torques take the controller out of the loop, so a
residual points at the plant: ground, friction, mass, (with commanded torques) the actuators.

Residual channels, each divided by its scale so that they are comparable: base position [m], base
orientation (rotation vector of measured^-1 * predicted) [rad], base linear and angular velocity (world
frame) [m/s, rad/s], joint positions [rad] and velocities [rad/s].
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
from dataclasses import dataclass

import numpy as np

from tal_core.robot_description import RobotDescription
from tal_sim_bridge.effects import ActuatorModel
from tal_sim_bridge.physics import Simulation

from .errors import MissingSignalsError
from .links import LowerLinkMasses
from .measured import MeasuredData
from .model import SimModel

LOG = logging.getLogger("tal.sim2real.segments")
CHANNEL_SCALES = {
    "base_position": 0.005,
    "base_orientation": 0.01,
    "base_lin_vel": 0.05,
    "base_ang_vel": 0.1,
    "joint_position": 0.005,
    "joint_velocity": 0.1,
}
CHANNEL_SIZES = {
    "base_position": 3,
    "base_orientation": 3,
    "base_lin_vel": 3,
    "base_ang_vel": 3,
    "joint_position": 12,
    "joint_velocity": 12,
}
ACTUATOR_WARMUP_STEPS = 60  # commands fed to the actuator model before a segment (delay + lag history)
DELIVERED_CACHE_SIZE = 4096
"""Segments' delivered torques kept by a ``SegmentSimulator`` (100 x 12 each: 40 MB at most)."""


@dataclass(frozen=True)
class SegmentPlan:
    """Segment start indices (joint-state samples), horizon [steps] and the comparison stride [steps]."""

    starts: np.ndarray
    horizon_steps: int = 100
    sample_every: int = 10

    @property
    def sample_offsets(self) -> np.ndarray:
        return np.arange(self.sample_every, self.horizon_steps + 1, self.sample_every)


def plan_segments(
    data: MeasuredData, start_s: float, end_s: float, every_s: float = 0.2, horizon_s: float = 0.1
) -> SegmentPlan:
    """Segments starting every ``every_s`` [s] in [start_s, end_s - horizon_s]."""
    horizon = int(round(horizon_s / data.dt_s))
    times = np.arange(start_s, end_s - horizon_s + 1e-9, every_s)
    starts = np.array([data.index_at(t) for t in times], dtype=int)
    starts = starts[(starts > ACTUATOR_WARMUP_STEPS) & (starts + horizon < len(data.t_s))]
    return SegmentPlan(np.unique(starts), horizon, max(1, int(round(0.01 / data.dt_s))))


class SegmentSimulator:
    """Open-loop segments of one recording: one PyBullet world reused across segments and across models
    that differ only in parameters that can change in place (ground, friction, joint friction, actuators); a
    payload rebuilds it. With ``workers`` > 1 the segments of each prediction are shared with ``workers`` - 1
    processes of their own world each (spawned): a segment starts from its measured state with fresh
    contacts, so it gives the same bits in whichever world it runs (``test_segment_replay``)."""

    def __init__(
        self, description: RobotDescription, data: MeasuredData, torque_source: str = "effort", workers: int = 1
    ) -> None:
        if data.base is None:
            raise MissingSignalsError("open-loop prediction", ["ground_truth/odom or state_estimate"])
        if torque_source == "effort" and data.effort_nm is None:
            raise MissingSignalsError("open-loop prediction with measured torques", ["joint_states.effort"])
        if torque_source == "command" and data.command_nm is None:
            raise MissingSignalsError("open-loop prediction with commanded torques", ["joint_command"])
        self.description = description
        self.data = data
        self.torque_source = torque_source
        self._torques = data.effort_nm if torque_source == "effort" else data.command_in_force()
        # (segment start, horizon, actuator effects) -> the torques the actuator model delivers over the
        # segment; valid for these torques only (cleared when they are replaced)
        self._delivered: dict[tuple, np.ndarray] = {}
        # the actuator model's output depends on the joint angles only through angle-dependent torque limits
        self._constant_limits = all(len(t.joint_angles_rad) == 1 for t in description.torque_limit_tables)
        start_xy = tuple(float(v) for v in data.base.position_m[0, :2])
        self._world = SegmentWorld(description, start_xy, torque_source)
        self._helpers = [_Helper(description, start_xy, torque_source) for _ in range(max(0, workers - 1))]
        self.simulated_steps = 0

    @property
    def torques(self) -> np.ndarray:
        """(samples, 12) joint torques [N m] that drive the segments: measured (``effort``) or commanded."""
        return self._torques

    @torques.setter
    def torques(self, value: np.ndarray) -> None:
        self._torques = value
        self._delivered.clear()

    def close(self) -> None:
        self._world.close()
        for helper in self._helpers:
            helper.close()
        self._helpers = []

    def predict(
        self,
        model: SimModel,
        plan: SegmentPlan,
        q_offset_rad: np.ndarray | None = None,
        link_mass_kg: np.ndarray | None = None,
    ) -> np.ndarray:
        """(segments, samples, STATE_SIZE) predicted states at the plan's sample offsets, laid out as in
        ``state_vector``. ``q_offset_rad``: (12,) encoder offsets (measured - true joint angle [rad]): the
        segments start from the measured angles minus them and the predicted angles are read through the
        same encoders (plus them). ``link_mass_kg``: (4,) extra mass at each leg's lower-link centre of mass
        [kg] (``links.LowerLinkMasses``; None: the description's masses)."""
        sim = self._world.configure(model)
        base = self.data.base
        assert base is not None
        inputs = []
        for i0 in plan.starts:
            state = (
                base.position_m[i0],
                base.quat_xyzw[i0],
                base.lin_vel_world_m_s[i0],
                base.ang_vel_world_rad_s[i0],
                self.data.q_rad[i0] if q_offset_rad is None else self.data.q_rad[i0] - q_offset_rad,
                self.data.qd_rad_s[i0],
            )
            delivered = self._segment_torques(sim, i0, plan.horizon_steps)
            if delivered is None:  # the torques as recorded, after the warm-up of the commands
                warmup = ACTUATOR_WARMUP_STEPS if self.torque_source == "command" else 0
                inputs.append((state, None, self.torques[i0 - warmup + 1 : i0 + plan.horizon_steps + 1]))
            else:
                inputs.append((state, delivered, None))
        offsets = plan.sample_offsets
        helpers = [h for h in self._helpers if h.alive] if len(inputs) > 1 else []
        if helpers:
            share = len(helpers) + 1
            for k, helper in enumerate(helpers, 1):
                helper.send(model, link_mass_kg, inputs[k::share], offsets, plan.horizon_steps)
            out = np.empty((len(inputs), len(offsets), STATE_SIZE))
            out[0::share] = self._world.run(model, link_mass_kg, inputs[0::share], offsets, plan.horizon_steps)
            for k, helper in enumerate(helpers, 1):
                part = helper.receive()
                if part is None:  # the helper failed (logged): its segments are run here
                    part = self._world.run(model, link_mass_kg, inputs[k::share], offsets, plan.horizon_steps)
                out[k::share] = part
        else:
            out = self._world.run(model, link_mass_kg, inputs, offsets, plan.horizon_steps)
        self.simulated_steps += len(inputs) * plan.horizon_steps
        if q_offset_rad is not None:
            out[..., Q_START : Q_START + len(q_offset_rad)] += q_offset_rad
        return out

    def _segment_torques(self, sim: Simulation, i0: int, horizon: int) -> np.ndarray | None:
        """(horizon, 12) torques the actuator model delivers over the segment from sample ``i0`` (commanded
        torques after ``ACTUATOR_WARMUP_STEPS`` of warm-up; measured ones pass unchanged but for the limits),
        computed with the bridge's ``ActuatorModel`` as ``Simulation.step`` would, once per segment and
        actuator effects (the candidates that change only the plant reuse them). None when the torque limits
        depend on the joint angles: then ``Simulation.step`` runs the actuator model on the simulated angles."""
        if not self._constant_limits:
            return None
        actuators = sim.actuators
        e = actuators.effects
        key = (i0, horizon, e.actuator_delay_s, e.actuator_lag_s, e.torque_gain, e.torque_limit_scale)
        out = self._delivered.get(key)
        if out is None:
            model = ActuatorModel(e, actuators.dt_s, actuators.tau_min, actuators.tau_max)
            if self.torque_source == "command":
                for k in range(i0 - ACTUATOR_WARMUP_STEPS + 1, i0 + 1):
                    model.delivered_torque(self.torques[k])
            tau_min, tau_max = self.description.torque_limits(self.description.nominal_joint_positions_rad)
            out = np.array(
                [
                    model.delivered_torque(np.asarray(self.torques[i0 + k], dtype=float), tau_min, tau_max)
                    for k in range(1, horizon + 1)
                ]
            )
            if len(self._delivered) >= DELIVERED_CACHE_SIZE:  # commanded torques under many actuator fits
                self._delivered.clear()
            self._delivered[key] = out
        return out


class SegmentWorld:
    """The PyBullet world that re-simulates segments: rebuilt for another payload (part of the URDF), the
    other parameters switched in place."""

    def __init__(self, description: RobotDescription, start_xy: tuple[float, float], torque_source: str) -> None:
        self.description = description
        self.start_xy = start_xy
        self.torque_source = torque_source
        self.sim: Simulation | None = None
        self.links: LowerLinkMasses | None = None
        self._urdf_key: tuple | None = None

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
            self.sim = None

    def configure(self, model: SimModel) -> Simulation:
        effects = model.effects
        if self.torque_source == "effort":  # measured torques are what the actuators delivered
            effects = dataclasses.replace(
                effects, actuator_delay_s=0.0, actuator_lag_s=0.0, torque_gain=1.0, torque_limit_scale=1.0
            )
        key = (model.robot, effects.payload_mass_kg, effects.payload_offset_m, model.course.name)
        if self.sim is None or key != self._urdf_key:
            self.close()
            self.sim = Simulation(self.description, model.course, effects=effects, initial_xy=self.start_xy)
            self.links = LowerLinkMasses(self.sim)
            self._urdf_key = key
        sim = self.sim
        sim.set_contact_model(model.course, effects)
        return sim

    def run(
        self, model: SimModel, link_mass_kg: np.ndarray | None, inputs: list, offsets: np.ndarray, horizon: int
    ) -> np.ndarray:
        """(len(inputs), len(offsets), STATE_SIZE) states at ``offsets`` of segments of ``horizon`` steps, each
        input (start state: base position, quaternion, linear and angular velocity, q, qd; the delivered
        torques (horizon, 12), or None and the recorded torques from the actuator model's warm-up on)."""
        sim = self.configure(model)
        assert self.links is not None
        self.links.apply(np.zeros(len(self.links.links)) if link_mass_kg is None else link_mass_kg)
        out = np.empty((len(inputs), len(offsets), STATE_SIZE))
        for s, (state, delivered, recorded) in enumerate(inputs):
            sim.set_state(*state)
            if delivered is None:
                warmup = len(recorded) - horizon
                for k in range(warmup):
                    sim.actuators.delivered_torque(recorded[k])
            j = 0
            for step in range(1, horizon + 1):
                if delivered is None:
                    sim.step(recorded[warmup + step - 1])
                else:
                    sim.step_delivered(delivered[step - 1])
                if step == offsets[j]:
                    out[s, j] = state_vector(sim)
                    j = min(j + 1, len(offsets) - 1)
        return out


class _Helper:
    """A process with a ``SegmentWorld`` of its own, simulating a share of each prediction's segments."""

    def __init__(self, description: RobotDescription, start_xy: tuple[float, float], torque_source: str) -> None:
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(
            target=_helper_loop, args=(child, description, start_xy, torque_source), daemon=True
        )
        self._process.start()
        child.close()
        self.alive = True

    def send(self, model, link_mass_kg, inputs, offsets, horizon) -> None:
        try:
            self._connection.send((model, link_mass_kg, inputs, offsets, horizon))
        except (OSError, ValueError) as exc:
            self._fail(f"cannot reach it: {exc}")

    def receive(self) -> np.ndarray | None:
        """The share's states, or None when the helper failed (then it is not used again)."""
        if not self.alive:
            return None
        try:
            status, payload = self._connection.recv()
        except (EOFError, OSError) as exc:
            self._fail(f"it ended: {exc!r}")
            return None
        if status != "ok":
            self._fail(payload)
            return None
        return payload

    def _fail(self, why: str) -> None:
        if self.alive:
            LOG.warning("segment helper process failed (%s): its segments run in this process", why)
        self.alive = False

    def close(self) -> None:
        if self.alive:
            try:
                self._connection.send(None)
            except (OSError, ValueError):
                pass
        self.alive = False
        self._process.join(timeout=10.0)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join()
        self._connection.close()


def _helper_loop(connection, description: RobotDescription, start_xy, torque_source: str) -> None:
    """Body of a ``_Helper`` process: runs the shares it is sent until it is sent None."""
    world = SegmentWorld(description, start_xy, torque_source)
    try:
        while True:
            try:
                request = connection.recv()
            except EOFError:
                return
            if request is None:
                return
            try:
                connection.send(("ok", world.run(*request)))
            except Exception as exc:  # reported to the parent, which runs the share itself
                connection.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        world.close()
        connection.close()


STATE_SIZE = 3 + 4 + 3 + 3 + 12 + 12
Q_START = 3 + 4 + 3 + 3  # joint angles in ``state_vector``


def state_vector(sim: Simulation) -> np.ndarray:
    """Base position, quaternion (x, y, z, w), world linear and angular velocity, q, qd."""
    position, quat = sim.base_pose()
    lin, ang = sim.base_velocity()
    q, qd = sim.joint_state()
    return np.concatenate([position, quat, lin, ang, q, qd])


def measured_vectors(data: MeasuredData, plan: SegmentPlan) -> np.ndarray:
    """The measured counterpart of ``SegmentSimulator.predict``."""
    base = data.base
    assert base is not None
    idx = plan.starts[:, None] + plan.sample_offsets[None, :]
    return np.concatenate(
        [
            base.position_m[idx],
            base.quat_xyzw[idx],
            base.lin_vel_world_m_s[idx],
            base.ang_vel_world_rad_s[idx],
            data.q_rad[idx],
            data.qd_rad_s[idx],
        ],
        axis=-1,
    )


def _quat_error(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Small-angle rotation vector [rad] of measured^-1 * predicted, (..., 3)."""
    mx, my, mz, mw = (measured[..., i] for i in range(4))
    px, py, pz, pw = (predicted[..., i] for i in range(4))
    # conj(m) * p
    w = mw * pw + mx * px + my * py + mz * pz
    x = mw * px - mx * pw - my * pz + mz * py
    y = mw * py + mx * pz - my * pw - mz * px
    z = mw * pz - mx * py + my * px - mz * pw
    sign = np.where(w < 0.0, -1.0, 1.0)
    return 2.0 * sign[..., None] * np.stack([x, y, z], axis=-1)


def channel_errors(measured: np.ndarray, predicted: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel errors (predicted - measured) in physical units, each (segments, samples, size)."""
    return {
        "base_position": predicted[..., 0:3] - measured[..., 0:3],
        "base_orientation": _quat_error(measured[..., 3:7], predicted[..., 3:7]),
        "base_lin_vel": predicted[..., 7:10] - measured[..., 7:10],
        "base_ang_vel": predicted[..., 10:13] - measured[..., 10:13],
        "joint_position": predicted[..., 13:25] - measured[..., 13:25],
        "joint_velocity": predicted[..., 25:37] - measured[..., 25:37],
    }


def scaled_residual(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """All channel errors divided by CHANNEL_SCALES, flattened (the fitting residual)."""
    errors = channel_errors(measured, predicted)
    parts = [errors[name] / CHANNEL_SCALES[name] for name in CHANNEL_SCALES]
    out = np.concatenate([p.reshape(len(measured), -1) for p in parts], axis=1).ravel()
    return np.nan_to_num(out, nan=1e3, posinf=1e3, neginf=-1e3)


def scaled_elements(measured: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """(segments, samples, 36) channel errors divided by CHANNEL_SCALES, components in CHANNEL_SCALES order
    (base position, orientation, linear and angular velocity, 12 joint positions, 12 joint velocities):
    the elements of ``scaled_residual`` by component."""
    errors = channel_errors(measured, predicted)
    out = np.concatenate([errors[name] / CHANNEL_SCALES[name] for name in CHANNEL_SCALES], axis=-1)
    return np.nan_to_num(out, nan=1e3, posinf=1e3, neginf=-1e3)


def component_channels() -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(channel -> boolean mask over the 36 components of ``scaled_elements``, joint index per component
    or -1 for the base channels)."""
    total = sum(CHANNEL_SIZES.values())
    masks, joint_of, start = {}, np.full(total, -1), 0
    for name in CHANNEL_SCALES:
        mask = np.zeros(total, dtype=bool)
        mask[start : start + CHANNEL_SIZES[name]] = True
        masks[name] = mask
        if name.startswith("joint_"):
            joint_of[start : start + CHANNEL_SIZES[name]] = np.arange(CHANNEL_SIZES[name])
        start += CHANNEL_SIZES[name]
    return masks, joint_of


def channel_rms(measured: np.ndarray, predicted: np.ndarray) -> dict[str, float]:
    """RMS error per channel in physical units (over segments, samples and components)."""
    return {name: float(np.sqrt(np.mean(err**2))) for name, err in channel_errors(measured, predicted).items()}
