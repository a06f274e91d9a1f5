"""Unit tests of the workflow's parts: vectorised torque path vs the bridge's ActuatorModel, the model's
parameter view and files, measured-data checks (units, stamps), the payload base frame in the bridge."""

from pathlib import Path

import numpy as np
import pytest

from tal_core.robot_description import load_robot_description
from tal_core.terrain import load_course
from tal_sim2real.errors import MeasuredDataError, ModelConfigError
from tal_sim2real.library import CANDIDATES, missing_signals
from tal_sim2real.measured import _keep_increasing, white_noise_std
from tal_sim2real.model import PARAMETER_NAMES, SimModel
from tal_sim2real.torque_path import delivered_torque
from tal_sim_bridge.effects import ActuatorModel, ModelEffects
from tal_sim_bridge.physics import Simulation


@pytest.mark.parametrize(
    "delay_s, lag_s, gain, scale",
    [(0.0, 0.0, 1.0, 1.0), (0.007, 0.0, 1.0, 1.0), (0.003, 0.01, 0.9, 0.5), (0.0, 0.004, 1.1, 0.3)],
)
def test_vectorised_torque_path_matches_the_bridge_actuator_model(delay_s, lag_s, gain, scale) -> None:
    rng = np.random.default_rng(0)
    n, dt = 400, 1e-3
    command = np.repeat(rng.normal(0.0, 60.0, (n // 4, 3)), 4, axis=0)  # 250 Hz held at 1 kHz
    low, high = np.full((n, 3), -80.0), np.full((n, 3), 90.0)
    effects = ModelEffects(actuator_delay_s=delay_s, actuator_lag_s=lag_s, torque_gain=gain, torque_limit_scale=scale)
    model = ActuatorModel(effects, dt, low[0], high[0])
    expected = np.array([model.delivered_torque(c) for c in command])
    got = delivered_torque(command, dt, low, high, delay_s=delay_s, lag_s=lag_s, gain=gain, limit_scale=scale)
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_effort_noise_estimate_of_a_smooth_torque_with_small_command_steps() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(2000) * 1e-3
    smooth = 40.0 * np.sin(2 * np.pi * 2.0 * t)[:, None] * np.ones((1, 12))
    steps = np.repeat(rng.normal(0.0, 0.5, (500, 12)), 4, axis=0)  # 250 Hz command updates
    assert white_noise_std(smooth + steps + rng.normal(0.0, 0.3, steps.shape)) == pytest.approx(0.3, rel=0.2)


def test_model_parameters_round_trip_through_the_sim_bridge_yaml(tmp_path: Path) -> None:
    nominal = SimModel.nominal("flat_rigid")
    changed = nominal.with_values(
        {
            "ground_stiffness_n_per_m": 25000.0,
            "payload_offset_y_m": 0.02,
            "payload_mass_kg": 3.0,
            "imu_gyro_bias_z_rad_s": -0.01,
        }
    )
    assert set(changed.differences(nominal)) == {
        "ground_stiffness_n_per_m",
        "payload_offset_y_m",
        "payload_mass_kg",
        "imu_gyro_bias_z_rad_s",
    }
    back = SimModel.from_yaml(changed.write_yaml(tmp_path / "m.yaml"))
    assert back.differences(changed) == {}
    assert back.course.properties(0.5, 0.0).stiffness_n_per_m == 25000.0
    with pytest.raises(ModelConfigError, match="unknown model parameter"):
        nominal.with_values({"warp_drive": 1.0})
    with pytest.raises(ModelConfigError, match="foot_friction must be > 0"):
        nominal.with_values({"foot_friction": 0.0})
    (tmp_path / "bad.yaml").write_text("hello: 1\n")
    with pytest.raises(ModelConfigError, match="not a sim_bridge parameter file"):
        SimModel.from_yaml(tmp_path / "bad.yaml")


def test_every_candidate_maps_to_model_parameters_and_names_its_signals() -> None:
    assert len(CANDIDATES) >= 10
    for candidate in CANDIDATES:
        assert set(candidate.parameter_names) <= set(PARAMETER_NAMES), candidate.name
        assert candidate.experiment
    delay = next(c for c in CANDIDATES if c.name == "actuator_delay")
    assert missing_signals(delay, {"joint_command"}) == ["joint_states.effort"]


def test_out_of_order_and_repeated_stamps_are_dropped_and_counted() -> None:
    rejected: dict[str, int] = {}
    keep = _keep_increasing(np.array([0.0, 0.001, 0.001, 0.0005, 0.002]), "/x", rejected)
    assert keep.tolist() == [True, True, False, False, True]
    assert rejected == {"/x": 2}


def test_joint_angles_in_degrees_are_refused(tmp_path: Path) -> None:
    from sensor_msgs.msg import JointState

    from tal_core.ros.bag_io import BagWriter
    from tal_sim2real.measured import load_measured

    description = load_robot_description("hyq")
    with BagWriter(tmp_path / "deg") as writer:
        writer.add_topic("/joint_states", "sensor_msgs/msg/JointState")
        for i in range(20):
            msg = JointState(name=list(description.joint_names), position=[45.0] * 12, velocity=[0.0] * 12)
            msg.header.stamp.nanosec = i * 1_000_000
            writer.write("/joint_states", msg, i * 1_000_000)
    with pytest.raises(MeasuredDataError, match="not in radians"):
        load_measured(tmp_path / "deg", description)
    with pytest.raises(MeasuredDataError, match="cannot read the bag"):
        load_measured(tmp_path / "nothing_here", description)


def test_payload_with_offset_keeps_the_base_link_frame_as_the_base_pose() -> None:
    """PyBullet reports the base CoM frame; a payload offset must not move the reported base."""
    description = load_robot_description("hyq")
    course = load_course("flat_rigid")
    plain = Simulation(description, course)
    loaded = Simulation(
        description, course, effects=ModelEffects(payload_mass_kg=10.0, payload_offset_m=(0.1, 0.05, 0.0))
    )
    try:
        p0, _ = plain.base_pose()
        p1, _ = loaded.base_pose()
        np.testing.assert_allclose(p1[:2], [0.0, 0.0], atol=1e-9)
        assert p1[2] == pytest.approx(p0[2], abs=1e-9)
        loaded.set_state(
            np.array([0.2, 0.1, 0.7]),
            np.array([0.0, 0.0, 0.3826834, 0.9238795]),
            np.array([0.1, 0.0, 0.0]),
            np.array([0.0, 0.0, 0.5]),
            description.nominal_joint_positions_rad,
            np.zeros(12),
        )
        pos, _ = loaded.base_pose()
        lin, ang = loaded.base_velocity()
        np.testing.assert_allclose(pos, [0.2, 0.1, 0.7], atol=1e-7)
        np.testing.assert_allclose(lin, [0.1, 0.0, 0.0], atol=1e-7)
        np.testing.assert_allclose(ang, [0.0, 0.0, 0.5], atol=1e-7)
    finally:
        plain.close()
        loaded.close()
