"""HyQ in MuJoCo (tal_lab.mujoco_hyq): the conversion keeps the robot tal knows and the controller holds it up."""

import mujoco
import numpy as np
import pytest
from tal_lab.mujoco_hyq import MujocoSimulation, build_robot

from tal_control.locomotion import LocomotionController
from tal_control.motion.gait import PRESETS
from tal_core.robot_description import load_robot_description
from tal_core.robot_model import RobotModel
from tal_core.state import BaseState
from tal_core.terrain import load_course


@pytest.fixture(scope="module")
def description():
    return load_robot_description("hyq")


def test_the_model_has_tals_joints_motors_and_mass(description) -> None:
    robot = build_robot(description, load_course("flat_rigid"))
    model = robot.model
    assert model.nu == 12
    driven = [
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, model.actuator_trnid[a, 0]) for a in robot.actuator_ids
    ]
    assert driven == list(description.joint_names)
    assert np.all(model.actuator_gear[:, 0] == 1.0)
    assert robot.total_mass_kg == pytest.approx(RobotModel(description).total_mass_kg, abs=1e-6)
    assert model.opt.timestep == pytest.approx(1e-3)
    # the URDF's joint damping is kept; the only colliding geoms are the feet and the floor
    assert np.allclose(model.dof_damping[robot.dof_adr], 0.1)
    colliding = {g for g in range(model.ngeom) if model.geom_contype[g] or model.geom_conaffinity[g]}
    assert colliding == {*robot.foot_geoms, robot.floor_geom}
    assert np.allclose(model.geom_size[list(robot.foot_geoms), 0], description.foot_radius_m)


def test_the_controller_holds_hyq_up_in_mujoco(description) -> None:
    course = load_course("flat_rigid")
    sim = MujocoSimulation(description, course)
    controller = LocomotionController(RobotModel(description), PRESETS["stand"])
    start = sim.robot_state().base_position_m.copy()
    tau = np.zeros(12)
    for k in range(500):
        if k % 4 == 0:
            s = sim.robot_state()
            base = BaseState(s.base_position_m, s.base_quat_xyzw, s.base_lin_vel_m_s, s.base_ang_vel_rad_s)
            tau = controller.tick(
                k * 1e-3,
                base,
                s.joint_position_rad,
                s.joint_velocity_rad_s,
                (0.0, 0.0, 0.0),
                lambda x, y: 0.0,
                lambda x, y: np.array([0.0, 0.0, 1.0]),
            ).tau
        state = sim.step(tau)
    assert abs(state.base_position_m[2] - sim.nominal_base_height_m) < 0.02
    assert np.linalg.norm(state.base_position_m[:2] - start[:2]) < 0.01
    contacts = sim.foot_contacts()
    assert all(c.in_contact for c in contacts)
    # the floor carries the robot: the feet's vertical forces add up to its weight (within 3 %)
    total = sum(c.force_n[2] for c in contacts)
    assert total == pytest.approx(sim.robot.total_mass_kg * 9.81, rel=0.03)
