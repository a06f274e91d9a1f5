"""Tests of the PyBullet simulation (tal_sim_bridge.physics) driven through BridgeCore, no ROS graph.

The robot stands under tal_control's StandHold, whose command is sent every 4 physics steps (250 Hz
control, 1 kHz physics) through the bridge's command hold, as the ROS graph does. Each scenario is
simulated once per module (module-scoped fixtures); the figures measured here are printed (pytest -s).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from tal_control.stand_hold import StandHold
from tal_core.robot_description import RobotDescription, load_robot_description
from tal_core.robot_model import RobotModel
from tal_core.terrain import load_course
from tal_sim_bridge.bridge_core import BridgeCore, ImuModel
from tal_sim_bridge.effects import GROUND_REFERENCE_DEPTH_M, ModelEffects
from tal_sim_bridge.errors import BridgeConfigError
from tal_sim_bridge.physics import GRAVITY_M_S2, FootContact, RobotState, Simulation

pytestmark = pytest.mark.slow

CONTROL_DECIMATION = 4  # physics steps per control tick (1 kHz / 250 Hz)
STEP_NS = 1_000_000
STAND_STEPS = 4000  # 4 s at 1 kHz
HYQ_MASS_KG = 86.77
GYRO_BIAS = (0.05, -0.03, 0.02)
ACCEL_BIAS = (0.2, -0.1, 0.3)


@dataclass
class Run:
    """What one simulated scenario leaves behind (the simulation itself is closed)."""

    course_name: str
    total_mass_kg: float
    state: RobotState                 # after the last step
    contacts: list[FootContact]       # after the last step
    late_contacts: list[list[FootContact]]  # every 10 steps over the last 0.5 s
    stiffness_n_per_m: np.ndarray     # (4,) ground stiffness under each foot at the end
    body_contacts: list[str]          # links other than feet touching the ground at the end
    imu: tuple[np.ndarray, np.ndarray]  # (specific force, angular rate) base frame, at the end
    base_positions: np.ndarray        # (steps, 3) after every step
    commanded: np.ndarray             # (steps, 12) torque the command hold asked for, per step
    delivered: np.ndarray             # (steps, 12) torque the actuators delivered, per step
    joint_positions: np.ndarray       # (steps, 12) joint angles at which each step's command was made


def simulate(description: RobotDescription, course_name: str, steps: int, *, hold: StandHold | None,
             effects: ModelEffects | None = None, drop_height_m: float = 0.0) -> Run:
    """Run ``steps`` physics steps; ``hold=None`` sends no command (the bridge damps the joints)."""
    course = load_course(course_name)
    sim = Simulation(description, course, effects=effects)
    try:
        if drop_height_m > 0.0:
            sim.reset(drop_height_m=drop_height_m)
        core = BridgeCore(sim)
        positions, commanded, delivered, joints, late = [], [], [], [], []
        state = sim.robot_state()
        for k in range(steps):
            if hold is not None and k % CONTROL_DECIMATION == 0:
                q, _ = sim.joint_state()
                f = hold.command(q)
                core.commands.submit(k * STEP_NS, description.joint_names, f["effort"], f["position"],
                                     f["velocity"], f["kp"], f["kd"])
            q, qd = sim.joint_state()
            commanded.append(core.commands.torque(q, qd))  # what core.step() applies next
            joints.append(q)
            state = core.step()
            positions.append(state.base_position_m)
            delivered.append(state.joint_torque_nm)
            if k >= steps - 500 and k % 10 == 9:
                late.append(sim.foot_contacts())
        contacts = sim.foot_contacts()
        stiffness = np.array([course.properties(c.position_m[0], c.position_m[1]).stiffness_n_per_m
                              for c in contacts])
        return Run(course_name, sim.total_mass_kg, state, contacts, late, stiffness,
                   sim.body_ground_contact(), core.imu.measure(state), np.array(positions),
                   np.array(commanded), np.array(delivered), np.array(joints))
    finally:
        sim.close()


def normal_forces(contacts: list[FootContact]) -> np.ndarray:
    return np.array([float(c.force_n @ c.normal) for c in contacts])


# --- fixtures: each scenario simulated once ------------------------------------------------------------
@pytest.fixture(scope="module")
def description() -> RobotDescription:
    return load_robot_description("hyq")


@pytest.fixture(scope="module")
def hold(description: RobotDescription) -> StandHold:
    return StandHold(RobotModel(description), 1500.0, 40.0)


@pytest.fixture(scope="module")
def stand_flat_t1(description: RobotDescription, hold: StandHold) -> Run:
    return simulate(description, "flat_t1", STAND_STEPS, hold=hold)


@pytest.fixture(scope="module")
def stand_flat_t2(description: RobotDescription, hold: StandHold) -> Run:
    return simulate(description, "flat_t2", STAND_STEPS, hold=hold)


@pytest.fixture(scope="module")
def stand_flat_t4(description: RobotDescription, hold: StandHold) -> Run:
    return simulate(description, "flat_t4", STAND_STEPS, hold=hold)


@pytest.fixture(scope="module")
def payload_flat_t4(description: RobotDescription, hold: StandHold) -> Run:
    return simulate(description, "flat_t4", 3000, hold=hold, effects=ModelEffects(payload_mass_kg=10.0))


# --- (a) penetration on soft ground --------------------------------------------------------------------
@pytest.mark.parametrize("course_name", ["flat_t1", "flat_t2"])
def test_soft_ground_penetration_matches_force_over_stiffness(request: pytest.FixtureRequest,
                                                              course_name: str) -> None:
    run: Run = request.getfixturevalue(f"stand_{course_name}")
    assert run.body_contacts == []
    force = normal_forces(run.contacts)
    penetration = np.array([c.penetration_m for c in run.contacts])
    from_force = force / run.stiffness_n_per_m
    static = run.total_mass_kg * GRAVITY_M_S2 / (4 * run.stiffness_n_per_m)
    print(f"\n{course_name}: K {run.stiffness_n_per_m[0]:.0f} N/m, static m*g/(n*K) {static[0] * 1e3:.2f} mm")
    for leg, f, p, pf in zip(("LF", "RF", "LH", "RH"), force, penetration, from_force, strict=True):
        print(f"  {leg}: F_n {f:7.1f} N  penetration {p * 1e3:7.3f} mm  F/K {pf * 1e3:7.3f} mm  "
              f"error {100 * (p - pf) / pf:+.3f} %")
    assert all(c.in_contact for c in run.contacts)
    np.testing.assert_allclose(penetration, from_force, rtol=0.05)
    for sample in run.late_contacts:  # over the last 0.5 s, not just the final step
        np.testing.assert_allclose([c.penetration_m for c in sample],
                                   normal_forces(sample) / run.stiffness_n_per_m, rtol=0.05)
    # At rest the feet carry the weight, so the mean penetration is the static expectation m*g/(n*K).
    assert force.sum() == pytest.approx(run.total_mass_kg * GRAVITY_M_S2, rel=0.01)
    assert penetration.mean() == pytest.approx(static[0], rel=0.02)


@pytest.fixture(scope="module")
def stand_flat_t1_power_law(description: RobotDescription, hold: StandHold) -> Run:
    return simulate(description, "flat_t1", STAND_STEPS, hold=hold, effects=ModelEffects(ground_contact_exponent=1.6))


def test_power_law_ground_sinks_as_its_law_says(stand_flat_t1_power_law: Run, stand_flat_t1: Run) -> None:
    """F_n = k delta (delta / delta_ref)^(n - 1) at rest, per foot; a different sinkage than the linear ground."""
    run = stand_flat_t1_power_law
    assert run.body_contacts == []
    force = normal_forces(run.contacts)
    depth = np.array([c.penetration_m for c in run.contacts])
    n = 1.6
    from_law = (force / run.stiffness_n_per_m * GROUND_REFERENCE_DEPTH_M ** (n - 1.0)) ** (1.0 / n)
    np.testing.assert_allclose(depth, from_law, rtol=0.05)
    assert force.sum() == pytest.approx(run.total_mass_kg * GRAVITY_M_S2, rel=0.01)
    linear_depth = np.mean([c.penetration_m for c in stand_flat_t1.contacts])
    assert abs(depth.mean() - linear_depth) > 0.1 * linear_depth


def test_ground_exponent_outside_its_range_is_rejected() -> None:
    for bad in (0.0, 5.0, float("nan")):
        with pytest.raises(BridgeConfigError, match="ground_contact_exponent"):
            ModelEffects(ground_contact_exponent=bad)


def test_switching_the_contact_model_equals_building_it(description: RobotDescription, hold: StandHold) -> None:
    """set_contact_model (used to re-simulate many candidate models) gives what a fresh Simulation gives."""
    course = load_course("flat_t1")
    power_law = ModelEffects(ground_contact_exponent=1.6)

    def stand(sim: Simulation) -> np.ndarray:
        sim.reset()
        for _ in range(300):
            q, qd = sim.joint_state()
            sim.step(hold.command(q)["effort"] + 1500.0 * (hold.command(q)["position"] - q) - 40.0 * qd, (q, qd))
        return np.array([c.penetration_m for c in sim.foot_contacts()])

    fresh = Simulation(description, course, effects=power_law)
    switched = Simulation(description, course)
    try:
        expected = stand(fresh)
        linear = stand(switched)
        switched.set_contact_model(course, power_law)
        np.testing.assert_allclose(stand(switched), expected, atol=1e-6)
        switched.set_contact_model(course, ModelEffects())
        np.testing.assert_allclose(stand(switched), linear, atol=1e-6)
        with pytest.raises(BridgeConfigError, match="payload"):
            switched.set_contact_model(course, ModelEffects(payload_mass_kg=3.0))
    finally:
        fresh.close()
        switched.close()


def test_normals_and_forces_point_out_of_flat_ground(stand_flat_t2: Run) -> None:
    for contact in stand_flat_t2.contacts:
        np.testing.assert_allclose(contact.normal, [0.0, 0.0, 1.0], atol=1e-9)
        assert contact.force_n[2] > 0.0
        assert np.linalg.norm(contact.velocity_m_s) < 0.01


# --- (b) rigid ground ----------------------------------------------------------------------------------
def test_rigid_ground_penetration_is_below_one_millimetre(stand_flat_t4: Run) -> None:
    penetration = np.array([c.penetration_m for c in stand_flat_t4.contacts])
    print(f"\nflat_t4 penetrations [mm]: {np.round(penetration * 1e3, 4)}")
    assert all(c.in_contact for c in stand_flat_t4.contacts)
    assert np.all(penetration < 1e-3)
    assert np.all(penetration > 0.0)
    assert normal_forces(stand_flat_t4.contacts).sum() == pytest.approx(HYQ_MASS_KG * GRAVITY_M_S2, rel=0.01)


# --- (c) mass ------------------------------------------------------------------------------------------
def test_total_mass_in_pybullet(stand_flat_t4: Run, hold: StandHold) -> None:
    assert stand_flat_t4.total_mass_kg == pytest.approx(HYQ_MASS_KG, abs=0.01)
    assert stand_flat_t4.total_mass_kg == pytest.approx(hold.model.total_mass_kg, abs=1e-9)


# --- (d) IMU -------------------------------------------------------------------------------------------
def test_imu_at_rest_reads_gravity_and_no_rotation(stand_flat_t4: Run) -> None:
    specific_force, angular_rate = stand_flat_t4.imu
    np.testing.assert_allclose(specific_force, [0.0, 0.0, GRAVITY_M_S2], atol=0.05)
    np.testing.assert_allclose(angular_rate, 0.0, atol=1e-3)


def test_configured_imu_biases_show_up_in_the_reading(description: RobotDescription, hold: StandHold) -> None:
    effects = ModelEffects(imu_gyro_bias_rad_s=GYRO_BIAS, imu_accel_bias_m_s2=ACCEL_BIAS)
    run = simulate(description, "flat_t4", 1000, hold=hold, effects=effects)
    specific_force, angular_rate = run.imu
    unbiased_force, unbiased_rate = ImuModel(ModelEffects()).measure(run.state)
    np.testing.assert_allclose(angular_rate - unbiased_rate, GYRO_BIAS, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(specific_force - unbiased_force, ACCEL_BIAS, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(angular_rate, GYRO_BIAS, atol=1e-3)  # at rest: the bias is all there is
    np.testing.assert_allclose(specific_force, np.add(ACCEL_BIAS, [0.0, 0.0, GRAVITY_M_S2]), atol=0.05)


# --- (e) payload ---------------------------------------------------------------------------------------
def test_payload_adds_its_mass_and_its_weight(payload_flat_t4: Run, stand_flat_t4: Run) -> None:
    assert payload_flat_t4.total_mass_kg - stand_flat_t4.total_mass_kg == pytest.approx(10.0, abs=1e-9)
    assert payload_flat_t4.body_contacts == []
    extra = normal_forces(payload_flat_t4.contacts).sum() - normal_forces(stand_flat_t4.contacts).sum()
    print(f"\npayload 10 kg: summed normal forces +{extra:.2f} N (expected {10 * GRAVITY_M_S2:.2f} N)")
    assert extra == pytest.approx(10.0 * GRAVITY_M_S2, abs=1.0)


# --- (f) actuator delay --------------------------------------------------------------------------------
def test_without_delay_the_delivered_torque_is_the_clipped_command(stand_flat_t4: Run,
                                                                   description: RobotDescription) -> None:
    run = stand_flat_t4
    limits = np.array([description.torque_limits(q)[1] for q in run.joint_positions])
    np.testing.assert_allclose(run.delivered, np.clip(run.commanded, -limits, limits), rtol=0, atol=1e-9)


def test_actuator_delay_shifts_the_delivered_torque_by_ten_steps(description: RobotDescription,
                                                                 hold: StandHold) -> None:
    delay_steps = 10
    run = simulate(description, "flat_t4", 300, hold=hold, effects=ModelEffects(actuator_delay_s=0.010))
    np.testing.assert_array_equal(run.delivered[:delay_steps], 0.0)
    # Delivered at step k: the command of step k - 10, clipped to the limits at step k's joint angles.
    limits = np.array([description.torque_limits(q)[1] for q in run.joint_positions])[delay_steps:]
    expected = np.clip(run.commanded[:-delay_steps], -limits, limits)
    np.testing.assert_allclose(run.delivered[delay_steps:], expected, rtol=0, atol=1e-9)
    # ... and not the current command: the stand controller's torque changes within 10 ms.
    assert np.max(np.abs(run.delivered[delay_steps:] - run.commanded[delay_steps:])) > 1.0


# --- (g) fall detection --------------------------------------------------------------------------------
def test_no_body_ground_contact_while_standing(stand_flat_t1: Run, stand_flat_t4: Run) -> None:
    assert stand_flat_t1.body_contacts == []
    assert stand_flat_t4.body_contacts == []


def test_body_ground_contact_after_collapsing_without_torque(description: RobotDescription) -> None:
    run = simulate(description, "flat_t4", 2000, hold=None, drop_height_m=0.05)
    print(f"\ncollapsed: links on the ground {run.body_contacts}, base z {run.state.base_position_m[2]:.3f}")
    # No command ever arrived: the bridge applied joint damping only.
    np.testing.assert_allclose(run.delivered, run.commanded, rtol=0, atol=1e-9)
    assert run.body_contacts != []
    assert run.state.base_position_m[2] < 0.4


# --- (h) determinism -----------------------------------------------------------------------------------
def test_identical_runs_are_bit_identical(description: RobotDescription, hold: StandHold,
                                          stand_flat_t1: Run) -> None:
    first = simulate(description, "flat_t1", 1000, hold=hold)
    second = simulate(description, "flat_t1", 1000, hold=hold)
    assert np.array_equal(first.base_positions, second.base_positions)
    assert np.array_equal(first.delivered, second.delivered)
    # The same as the first second of the 4 s run made earlier in this process.
    assert np.array_equal(first.base_positions, stand_flat_t1.base_positions[:1000])


# --- (i) reset -----------------------------------------------------------------------------------------
@pytest.fixture()
def rigid_sim(description: RobotDescription):
    sim = Simulation(description, load_course("flat_t4"))
    yield sim
    sim.close()


@pytest.mark.parametrize("initial_xy", [(50.0, 0.0), (0.0, -3.0), (-1.9, 0.0)],
                         ids=["far-outside", "beside", "hind-feet-outside"])
def test_reset_outside_the_course_extent_is_rejected(rigid_sim: Simulation,
                                                     initial_xy: tuple[float, float]) -> None:
    with pytest.raises(BridgeConfigError, match=r"initial position .* puts a foot outside the course extent"):
        rigid_sim.reset(initial_xy)


def test_a_valid_reset_after_a_rejected_one_restores_the_nominal_start(rigid_sim: Simulation,
                                                                       description: RobotDescription) -> None:
    start = rigid_sim.robot_state()
    with pytest.raises(BridgeConfigError):
        rigid_sim.reset((50.0, 0.0))
    rigid_sim.reset()
    again = rigid_sim.robot_state()
    np.testing.assert_array_equal(again.base_position_m, start.base_position_m)
    np.testing.assert_array_equal(again.joint_position_rad, start.joint_position_rad)
    assert rigid_sim.step_count == 0
    # Feet on the ground: the lowest foot sphere touches z = 0.
    lowest = min(c.position_m[2] for c in rigid_sim.foot_contacts())
    assert lowest == pytest.approx(description.foot_radius_m, abs=1e-6)  # PyBullet link states: ~1e-8


def test_construction_outside_the_extent_is_rejected_without_leaking(
        description: RobotDescription, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where the prepared URDF is written
    with pytest.raises(BridgeConfigError, match=r"outside the course extent"):
        Simulation(description, load_course("flat_t4"), initial_xy=(50.0, 0.0))
    assert list(tmp_path.glob("tal_robot_*.urdf")) == []


def test_close_removes_the_prepared_urdf(description: RobotDescription, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    sim = Simulation(description, load_course("flat_t4"))
    assert len(list(tmp_path.glob("tal_robot_*.urdf"))) == 1
    sim.close()
    sim.close()  # idempotent
    assert list(tmp_path.glob("tal_robot_*.urdf")) == []


def test_soft_boxes_reach_under_their_neighbours(description: RobotDescription) -> None:
    """The T1 strip's collision box extends SOFT_BOX_OVERLAP_M past its patch on every side (a foot sunk
    next to the patch side must not be pushed out through it); rigid boxes keep their size."""
    from tal_sim_bridge.physics import SOFT_BOX_OVERLAP_M

    course = load_course("stance_course")
    sim = Simulation(description, course, time_step_s=1e-3)
    try:
        boxes = course.primitives()
        for box, body in zip(boxes, sim.ground_bodies):
            half = np.array(sim.client.getCollisionShapeData(body, -1)[0][3]) / 2.0
            expected = np.array(box.half_extents_xyz)
            if box.stiffness_n_per_m < 1e5:
                expected[:2] += SOFT_BOX_OVERLAP_M
            np.testing.assert_allclose(half, expected, atol=1e-9)
        assert any(b.stiffness_n_per_m < 1e5 for b in boxes)
    finally:
        sim.close()
