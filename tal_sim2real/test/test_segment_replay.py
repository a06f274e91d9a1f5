"""The open-loop segment replay's shortcuts (issue 34, the workflow's time) must not change a single bit of
its predictions: the torques the actuator model delivers are computed ahead per segment and stepped with
``Simulation.step_delivered``, instead of ``Simulation.step`` running the actuator model every physics step.
The reference here is the plain replay: teleport to the measured state, feed the commands' warm-up to the
actuator model, then ``Simulation.step`` with each measured or commanded torque."""

from __future__ import annotations

import numpy as np
import pytest

from tal_core.robot_description import load_robot_description
from tal_core.terrain import load_course
from tal_sim2real.measured import BaseTrajectory, MeasuredData
from tal_sim2real.model import SimModel
from tal_sim2real.segments import ACTUATOR_WARMUP_STEPS, STATE_SIZE, SegmentPlan, SegmentSimulator, state_vector
from tal_sim_bridge.physics import Simulation

DT = 1e-3
STEPS = 700


@pytest.fixture(scope="module")
def stepping() -> MeasuredData:
    """0.7 s of HyQ standing on flat ground under a PD controller whose reference sways every joint (so the
    joints move, friction acts and the feet load and unload), recorded like a bag: base state, joint states,
    the delivered torques as the measured effort and the PD torques as the commands."""
    description = load_robot_description("hyq")
    sim = Simulation(description, load_course("flat_rigid"))
    q0 = description.nominal_joint_positions_rad
    n = STEPS
    t = np.arange(n) * DT
    pos, quat, lin, ang = np.zeros((n, 3)), np.zeros((n, 4)), np.zeros((n, 3)), np.zeros((n, 3))
    q, qd, effort, command = (np.zeros((n, 12)) for _ in range(4))
    phase = np.arange(12)
    try:
        for i in range(n):
            qi, qdi = sim.joint_state()
            ref = q0 + 0.08 * np.sin(2.0 * np.pi * 3.0 * t[i] + phase)
            command[i] = 300.0 * (ref - qi) - 8.0 * qdi
            sim.step(command[i])
            state = sim.robot_state()
            pos[i], quat[i] = state.base_position_m, state.base_quat_xyzw
            lin[i], ang[i] = state.base_lin_vel_m_s, state.base_ang_vel_rad_s
            q[i], qd[i], effort[i] = state.joint_position_rad, state.joint_velocity_rad_s, state.joint_torque_nm
    finally:
        sim.close()
    rot = np.array([np.eye(3)] * n)
    base = BaseTrajectory(pos, quat, rot, lin, ang, "/ground_truth/odom")
    return MeasuredData(
        "stand", list(description.joint_names), t, DT, q, qd, effort, base=base, command_t_s=t - DT, command_nm=command
    )


def _plain_replay(segments: SegmentSimulator, model: SimModel, plan: SegmentPlan, link_mass_kg=None) -> np.ndarray:
    """``SegmentSimulator.predict`` as it was before the shortcuts: ``Simulation.step`` every physics step."""
    sim = segments._world.configure(model)
    segments._world.links.apply(np.zeros(4) if link_mass_kg is None else link_mass_kg)
    data, base = segments.data, segments.data.base
    offsets = plan.sample_offsets
    out = np.empty((len(plan.starts), len(offsets), STATE_SIZE))
    for s, i0 in enumerate(plan.starts):
        sim.set_state(
            base.position_m[i0],
            base.quat_xyzw[i0],
            base.lin_vel_world_m_s[i0],
            base.ang_vel_world_rad_s[i0],
            data.q_rad[i0],
            data.qd_rad_s[i0],
        )
        if segments.torque_source == "command":
            for k in range(i0 - ACTUATOR_WARMUP_STEPS + 1, i0 + 1):
                sim.actuators.delivered_torque(segments.torques[k])
        j = 0
        for step in range(1, plan.horizon_steps + 1):
            sim.step(segments.torques[i0 + step])
            if step == offsets[j]:
                out[s, j] = state_vector(sim)
                j = min(j + 1, len(offsets) - 1)
    return out


NOMINAL = SimModel.nominal("flat_rigid")
MODELS = {
    "nominal": NOMINAL,
    "payload with offset": NOMINAL.with_values(
        {"payload_mass_kg": 6.0, "payload_offset_x_m": -0.03, "payload_offset_y_m": -0.12}
    ),
    "joint friction": NOMINAL.with_values(
        {"joint_viscous_friction_nms_per_rad": 1.2, "joint_coulomb_friction_nm": 2.5}
    ),
    "soft ground": NOMINAL.with_values({"ground_stiffness_n_per_m": 2e4, "ground_damping_ns_per_m": 500.0}),
    "power-law ground": NOMINAL.with_values(
        {"ground_stiffness_n_per_m": 2e4, "ground_damping_ns_per_m": 500.0, "ground_contact_exponent": 1.3}
    ),
    "actuators": NOMINAL.with_values(
        {"actuator_delay_s": 0.004, "actuator_lag_s": 0.003, "torque_gain": 0.9, "torque_limit_scale": 0.3}
    ),
}


@pytest.mark.parametrize(("source", "workers"), [("effort", 1), ("command", 1), ("effort", 2), ("command", 3)])
def test_segments_replay_bit_for_bit_as_with_the_bridges_step(
    stepping: MeasuredData, source: str, workers: int
) -> None:
    """Also with the segments shared among processes (``workers``): each in a world of its own."""
    description = load_robot_description("hyq")
    plan = SegmentPlan(np.array([100, 260, 420, 580, 340]), 100, 10)
    fast = SegmentSimulator(description, stepping, source, workers=workers)
    plain = SegmentSimulator(description, stepping, source)
    try:
        for name, model in MODELS.items():
            np.testing.assert_array_equal(fast.predict(model, plan), _plain_replay(plain, model, plan), err_msg=name)
        mass = np.array([0.0, 2.5, 0.0, 0.0])
        np.testing.assert_array_equal(
            fast.predict(NOMINAL, plan, link_mass_kg=mass), _plain_replay(plain, NOMINAL, plan, mass)
        )
        # the torques replaced (the noise floor's perturbed ones, a sensor gain's corrected ones): not the
        # segments' torques computed for the previous ones
        scaled = fast.torques * 0.7
        fast.torques, plain.torques = scaled, scaled
        np.testing.assert_array_equal(fast.predict(NOMINAL, plan), _plain_replay(plain, NOMINAL, plan))
        offset = np.r_[np.zeros(8), 0.01, np.zeros(3)]
        assert fast.simulated_steps == (len(MODELS) + 2) * len(plan.starts) * plan.horizon_steps
        with_offset = fast.predict(NOMINAL, plan, q_offset_rad=offset)
        saved = plain.data.q_rad.copy()
        plain.data.q_rad[plan.starts] -= offset  # what an encoder offset means: the true angles are these
        try:
            reference = _plain_replay(plain, NOMINAL, plan)
        finally:
            plain.data.q_rad[:] = saved
        reference[..., 13:25] += offset
        np.testing.assert_array_equal(with_offset, reference)
    finally:
        fast.close()
        plain.close()
    assert np.abs(stepping.qd_rad_s).max() > 0.3  # the joints move: friction acts


# -- predictions asked for again ------------------------------------------------------------------------------
class _CountingSim:
    """A segment simulator stand-in: counts its re-simulations; its prediction depends on the torques."""

    def __init__(self) -> None:
        self.torques = np.ones((50, 12))
        self.calls = 0

    def predict(self, model: SimModel, plan: SegmentPlan, q_offset_rad=None, link_mass_kg=None) -> np.ndarray:
        self.calls += 1
        out = np.full((len(plan.starts), len(plan.sample_offsets), STATE_SIZE), float(self.torques.sum()))
        out[..., 0] += model.values()["payload_mass_kg"] + (0.0 if q_offset_rad is None else q_offset_rad.sum())
        return out


def _split(values: dict) -> tuple[SimModel, dict]:
    offset = values.get("encoder_offset_lf_haa_joint_rad", 0.0)
    extras = {"q_offset_rad": np.r_[offset, np.zeros(11)]} if offset != 0.0 else {}
    return NOMINAL.with_values({k: v for k, v in values.items() if not k.startswith("encoder_")}), extras


def test_a_prediction_is_simulated_once_per_model_plan_and_torques() -> None:
    from tal_sim2real.dynamics import MemoisedPredictions

    sim = _CountingSim()
    predict = MemoisedPredictions(sim, _split)
    plan, other_plan = SegmentPlan(np.array([5, 20]), 10, 5), SegmentPlan(np.array([5, 20]), 10, 5)
    first = predict({"payload_mass_kg": 2.0}, plan)
    assert not first.flags.writeable  # shared: nobody may change it
    np.testing.assert_array_equal(predict({"payload_mass_kg": 2.0}, plan), first)
    predict({"payload_mass_kg": 2.0, "encoder_offset_lf_haa_joint_rad": 0.0}, plan)  # an offset of 0: the same
    assert sim.calls == 1 and predict.hits == 2
    predict({"payload_mass_kg": 2.0, "encoder_offset_lf_haa_joint_rad": 0.01}, plan)
    predict({"payload_mass_kg": 2.0}, other_plan)
    predict({"payload_mass_kg": 3.0}, plan)
    assert sim.calls == 4
    predict({"payload_mass_kg": 2.0, "payload_offset_x_m": -0.0}, plan)  # -0.0: not taken for 0.0
    assert sim.calls == 5
    raw = sim.torques
    sim.torques = raw * 0.5  # e.g. a torque-sensor gain: the same model driven otherwise
    assert predict({"payload_mass_kg": 2.0}, plan)[0, 0, 0] != first[0, 0, 0] and sim.calls == 6
    sim.torques = raw
    np.testing.assert_array_equal(predict({"payload_mass_kg": 2.0}, plan), first)
    assert sim.calls == 6


def test_the_noise_floor_averages_its_draws_and_leaves_the_data_as_it_was(
    stepping: MeasuredData, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The held-out floor (the remainder verdict's yardstick) is the mean over ``draws`` perturbations, seeds
    0, 1, ...; one draw is the first of them; the measured data and torques are restored after each."""
    from tal_sim2real.dynamics import _noise_floor_parts

    description = load_robot_description("hyq")
    plan = SegmentPlan(np.array([100, 300, 500]), 60, 10)
    sim = SegmentSimulator(description, stepping, "effort")
    q, qd, tau = stepping.q_rad.copy(), stepping.qd_rad_s.copy(), sim.torques.copy()
    try:
        clean = sim.predict(NOMINAL, plan)
        one = _noise_floor_parts(sim, stepping, NOMINAL, plan, clean)
        two = _noise_floor_parts(sim, stepping, NOMINAL, plan, clean, draws=2)
        np.testing.assert_array_equal(_noise_floor_parts(sim, stepping, NOMINAL, plan, clean, draws=1), one)
        real_rng = np.random.default_rng
        with monkeypatch.context() as patch:   # the single draw of seed 1
            patch.setattr(np.random, "default_rng", lambda seed: real_rng(seed + 1))
            second = _noise_floor_parts(sim, stepping, NOMINAL, plan, clean)
        np.testing.assert_allclose(two, (one + second) / 2.0, rtol=1e-12)
        assert one.sum() != pytest.approx(second.sum(), rel=1e-3)  # the draws differ
        np.testing.assert_array_equal(stepping.q_rad, q)
        np.testing.assert_array_equal(stepping.qd_rad_s, qd)
        np.testing.assert_array_equal(sim.torques, tau)
        with pytest.raises(ValueError, match="draws"):
            _noise_floor_parts(sim, stepping, NOMINAL, plan, clean, draws=0)
    finally:
        sim.close()
