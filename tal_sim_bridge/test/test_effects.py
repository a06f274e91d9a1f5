"""Tests of tal_sim_bridge.effects: the actuator torque path and the validation of model effects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tal_sim_bridge.effects import COULOMB_SMOOTHING_RAD_S, ActuatorModel, ModelEffects
from tal_sim_bridge.errors import BridgeConfigError

DT_S = 1e-3
N_JOINTS = 3
TAU_MAX = np.array([100.0, 150.0, 200.0])  # [N m] deliberately different per joint


def actuator(**effects: float) -> ActuatorModel:
    return ActuatorModel(ModelEffects(**effects), DT_S, -TAU_MAX, TAU_MAX)


def run(model: ActuatorModel, commands: np.ndarray) -> np.ndarray:
    """Delivered torques (steps, joints) for a sequence of commanded torques (steps, joints)."""
    return np.array([model.delivered_torque(c) for c in commands])


# --- transport delay ----------------------------------------------------------------------------------
@pytest.mark.parametrize("delay_steps", [0, 1, 5, 10])
def test_delay_shifts_an_impulse_by_exactly_n_steps(delay_steps: int) -> None:
    model = actuator(actuator_delay_s=delay_steps * DT_S)
    assert model.delay_steps == delay_steps
    impulse = np.array([7.0, -3.0, 11.0])
    commands = np.zeros((30, N_JOINTS))
    commands[4] = impulse
    delivered = run(model, commands)
    expected = np.zeros_like(commands)
    expected[4 + delay_steps] = impulse
    np.testing.assert_array_equal(delivered, expected)


def test_delay_outputs_zero_until_the_first_command_has_travelled_through() -> None:
    model = actuator(actuator_delay_s=3 * DT_S)
    delivered = run(model, np.tile([1.0, 2.0, 3.0], (6, 1)))
    np.testing.assert_array_equal(delivered[:3], 0.0)
    np.testing.assert_array_equal(delivered[3:], np.tile([1.0, 2.0, 3.0], (3, 1)))


def test_delay_is_rounded_to_whole_physics_steps() -> None:
    assert actuator(actuator_delay_s=4.6e-3).delay_steps == 5
    assert actuator(actuator_delay_s=4.4e-3).delay_steps == 4


def test_a_ramp_is_delayed_sample_by_sample() -> None:
    model = actuator(actuator_delay_s=7 * DT_S)
    commands = np.outer(np.arange(40.0), [1.0, -0.5, 2.0])
    delivered = run(model, commands)
    np.testing.assert_array_equal(delivered[7:], commands[:-7])


def test_reset_forgets_commands_in_flight() -> None:
    model = actuator(actuator_delay_s=2 * DT_S, actuator_lag_s=0.01)
    run(model, np.ones((5, N_JOINTS)))
    model.reset()
    np.testing.assert_array_equal(run(model, np.zeros((5, N_JOINTS))), 0.0)


# --- first-order lag -----------------------------------------------------------------------------------
@pytest.mark.parametrize("lag_s", [0.005, 0.02, 0.1])
def test_lag_step_response_is_the_exact_first_order_response(lag_s: float) -> None:
    model = actuator(actuator_lag_s=lag_s)
    steps = int(round(3 * lag_s / DT_S))
    delivered = run(model, np.ones((steps, N_JOINTS)))
    # After n updates with the input held at 1 the state is x(n dt) = 1 - exp(-n dt / T), exactly.
    t = DT_S * np.arange(1, steps + 1)
    np.testing.assert_allclose(delivered, np.tile(1.0 - np.exp(-t / lag_s), (N_JOINTS, 1)).T, rtol=1e-12)
    n_at_time_constant = int(round(lag_s / DT_S))
    np.testing.assert_allclose(delivered[n_at_time_constant - 1], 1.0 - math.exp(-1.0), rtol=1e-12)


def test_lag_scales_with_the_step_amplitude_per_joint() -> None:
    model = actuator(actuator_lag_s=0.02)
    amplitude = np.array([10.0, -40.0, 90.0])
    delivered = run(model, np.tile(amplitude, (20, 1)))
    np.testing.assert_allclose(delivered[-1], (1.0 - math.exp(-1.0)) * amplitude, rtol=1e-12)


def test_without_lag_the_command_passes_straight_through() -> None:
    model = actuator()
    commands = np.random.default_rng(0).uniform(-90.0, 90.0, (50, N_JOINTS))
    np.testing.assert_allclose(run(model, commands), commands, rtol=0.0, atol=1e-12)


def test_delay_then_lag() -> None:
    model = actuator(actuator_delay_s=5 * DT_S, actuator_lag_s=0.01)
    delivered = run(model, np.ones((25, N_JOINTS)))
    np.testing.assert_array_equal(delivered[:5], 0.0)
    t = DT_S * np.arange(1, 21)
    np.testing.assert_allclose(delivered[5:, 0], 1.0 - np.exp(-t / 0.01), rtol=1e-12)


# --- gain and saturation -------------------------------------------------------------------------------
def test_torque_gain_scales_the_delivered_torque() -> None:
    model = actuator(torque_gain=0.8)
    np.testing.assert_allclose(model.delivered_torque(np.array([10.0, -20.0, 50.0])), [8.0, -16.0, 40.0])


def test_saturation_at_the_nominal_limits() -> None:
    model = actuator()
    delivered = model.delivered_torque(np.array([500.0, -500.0, 199.0]))
    np.testing.assert_array_equal(delivered, [100.0, -150.0, 199.0])


def test_saturation_at_the_scaled_limits() -> None:
    model = actuator(torque_limit_scale=0.5)
    delivered = model.delivered_torque(np.array([60.0, -80.0, 99.0]))
    np.testing.assert_array_equal(delivered, [50.0, -75.0, 99.0])


def test_gain_is_applied_before_saturation() -> None:
    model = actuator(torque_gain=2.0)
    delivered = model.delivered_torque(np.array([60.0, 60.0, -60.0]))
    np.testing.assert_array_equal(delivered, [100.0, 120.0, -120.0])


def test_joint_angle_dependent_limits_are_taken_per_call_and_scaled() -> None:
    model = actuator(torque_limit_scale=0.5)
    command = np.array([80.0, -80.0, 80.0])
    np.testing.assert_array_equal(model.delivered_torque(command), [50.0, -75.0, 80.0])
    low, high = np.array([-20.0, -30.0, -40.0]), np.array([60.0, 70.0, 80.0])
    np.testing.assert_array_equal(model.delivered_torque(command, low, high), [30.0, -15.0, 40.0])
    # The next call without per-call limits falls back to the construction-time limits.
    np.testing.assert_array_equal(model.delivered_torque(command), [50.0, -75.0, 80.0])


# --- joint friction ------------------------------------------------------------------------------------
def test_viscous_friction_opposes_the_velocity_proportionally() -> None:
    model = actuator(joint_viscous_friction_nms_per_rad=2.5)
    qd = np.array([-2.0, 0.0, 4.0])
    np.testing.assert_allclose(model.friction_torque(qd), [5.0, 0.0, -10.0])


def test_coulomb_friction_has_constant_magnitude_against_the_motion() -> None:
    model = actuator(joint_coulomb_friction_nm=3.0)
    qd = np.array([-1.0, 0.0, 0.5])
    np.testing.assert_allclose(model.friction_torque(qd), [3.0, 0.0, -3.0], rtol=1e-12, atol=0.0)
    # Smoothed around zero speed: 76% of the magnitude at the smoothing speed, odd in the velocity.
    smooth = model.friction_torque(np.array([COULOMB_SMOOTHING_RAD_S, -COULOMB_SMOOTHING_RAD_S, 0.0]))
    np.testing.assert_allclose(smooth[:2], [-3.0 * math.tanh(1.0), 3.0 * math.tanh(1.0)], rtol=1e-12)
    assert abs(smooth[0]) == pytest.approx(0.76 * 3.0, abs=0.01)


def test_viscous_and_coulomb_friction_add_up() -> None:
    model = actuator(joint_viscous_friction_nms_per_rad=2.0, joint_coulomb_friction_nm=1.5)
    friction = model.friction_torque(np.array([3.0, -3.0, 0.0]))
    np.testing.assert_allclose(friction, [-7.5, 7.5, 0.0], rtol=1e-12)


def test_no_friction_by_default_and_friction_stays_out_of_the_delivered_torque() -> None:
    model = actuator()
    np.testing.assert_array_equal(model.friction_torque(np.array([5.0, -5.0, 0.0])), 0.0)
    rubbing = actuator(joint_viscous_friction_nms_per_rad=3.0)
    np.testing.assert_array_equal(rubbing.delivered_torque(np.array([1.0, 2.0, 3.0])), [1.0, 2.0, 3.0])


def test_actuator_rejects_a_non_positive_time_step() -> None:
    with pytest.raises(BridgeConfigError, match="time step must be > 0"):
        ActuatorModel(ModelEffects(), 0.0, -TAU_MAX, TAU_MAX)


# --- ModelEffects validation ---------------------------------------------------------------------------
@pytest.mark.parametrize(("kwargs", "message"), [
    ({"actuator_delay_s": -0.001}, r"'actuator_delay_s' must be a finite number >= 0, got -0\.001"),
    ({"actuator_lag_s": -1.0}, r"'actuator_lag_s' must be a finite number >= 0"),
    ({"actuator_lag_s": math.nan}, r"'actuator_lag_s' must be a finite number >= 0, got nan"),
    ({"actuator_delay_s": math.inf}, r"'actuator_delay_s' must be a finite number >= 0, got inf"),
    ({"joint_viscous_friction_nms_per_rad": -0.1}, r"'joint_viscous_friction_nms_per_rad' must be"),
    ({"joint_coulomb_friction_nm": math.nan}, r"'joint_coulomb_friction_nm' must be"),
    ({"payload_mass_kg": -5.0}, r"'payload_mass_kg' must be a finite number >= 0"),
    ({"torque_gain": 0.0}, r"'torque_gain' must be a finite number > 0, got 0\.0"),
    ({"torque_gain": -1.0}, r"'torque_gain' must be a finite number > 0"),
    ({"torque_gain": math.nan}, r"'torque_gain' must be a finite number > 0, got nan"),
    ({"torque_limit_scale": 0.0}, r"'torque_limit_scale' must be a finite number > 0"),
    ({"payload_offset_m": (0.1, 0.2)}, r"'payload_offset_m' must be 3 finite numbers, got \(0\.1, 0\.2\)"),
    ({"imu_gyro_bias_rad_s": (0.0, 0.0, 0.0, 0.0)}, r"'imu_gyro_bias_rad_s' must be 3 finite numbers"),
    ({"imu_accel_bias_m_s2": (0.0, math.nan, 0.0)}, r"'imu_accel_bias_m_s2' must be 3 finite numbers"),
])
def test_invalid_effects_are_rejected_with_the_parameter_name(kwargs: dict, message: str) -> None:
    with pytest.raises(BridgeConfigError, match=message):
        ModelEffects(**kwargs)


def test_from_mapping_rejects_unknown_keys_and_lists_the_known_ones() -> None:
    with pytest.raises(BridgeConfigError, match=r"unknown model effect\(s\) \['actuator_delay_ms'\]; known: "
                                                r"\[.*'actuator_delay_s'.*\]"):
        ModelEffects.from_mapping({"actuator_delay_ms": 10.0, "torque_gain": 0.9})


def test_from_mapping_validates_values_too() -> None:
    with pytest.raises(BridgeConfigError, match=r"'torque_gain' must be a finite number > 0"):
        ModelEffects.from_mapping({"torque_gain": 0})
    with pytest.raises(BridgeConfigError, match=r"'payload_offset_m' must be 3 finite numbers"):
        ModelEffects.from_mapping({"payload_offset_m": [0.0, 1.0]})


def test_from_mapping_converts_parameter_values() -> None:
    effects = ModelEffects.from_mapping({"actuator_delay_s": 0.01, "payload_mass_kg": 5,
                                         "imu_gyro_bias_rad_s": [0.01, 0, -0.02]})
    assert effects == ModelEffects(actuator_delay_s=0.01, payload_mass_kg=5.0,
                                   imu_gyro_bias_rad_s=(0.01, 0.0, -0.02))
    assert isinstance(effects.imu_gyro_bias_rad_s, tuple)
    assert ModelEffects.from_mapping({}) == ModelEffects()


# --- active() ------------------------------------------------------------------------------------------
def test_active_is_empty_for_the_nominal_model() -> None:
    assert ModelEffects().active() == {}
    assert ModelEffects.from_mapping({"torque_gain": 1.0, "payload_offset_m": [0, 0, 0]}).active() == {}


def test_active_lists_only_the_effects_that_differ_from_the_default() -> None:
    effects = ModelEffects(actuator_delay_s=0.01, torque_gain=0.9, imu_gyro_bias_rad_s=(0.0, 0.0, 0.01))
    assert effects.active() == {"actuator_delay_s": 0.01, "torque_gain": 0.9,
                                "imu_gyro_bias_rad_s": (0.0, 0.0, 0.01)}
