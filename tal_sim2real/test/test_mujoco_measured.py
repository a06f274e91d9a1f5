"""A HyQ trot recorded in MuJoCo (tal_lab.mujoco_hyq) is measured data the workflow reads (issue 34 item 5)."""

from pathlib import Path

import numpy as np
import pytest
from tal_lab.mujoco_hyq import record_trot

from tal_core.robot_description import load_robot_description
from tal_core.ros.bag_io import BagReader
from tal_sim2real.measured import TOPICS, load_measured


def test_the_recorded_trot_is_a_bag_the_workflow_reads(tmp_path: Path) -> None:
    description = load_robot_description("hyq")
    run = record_trot(tmp_path / "mujoco_trot", duration_s=1.0, progress=False)
    assert not run.fell
    topics = set(BagReader(run.bag).topics())
    assert {
        TOPICS[k] for k in ("joint_states", "imu", "ground_truth", "joint_command", "cmd_vel", "contacts")
    } <= topics
    data = load_measured(run.bag, description)
    assert data.dt_s == pytest.approx(1e-3)
    assert len(data.t_s) == 1001
    for signal in (data.effort_nm, data.gyro_rad_s, data.base, data.command_nm, data.cmd_vel, data.contact_in):
        assert signal is not None
    base = data.base
    # frames: the recorded world-frame velocities are the derivatives of the recorded pose
    lin = np.gradient(base.position_m, data.t_s, axis=0)
    assert np.sqrt(np.mean((lin[5:-5] - base.lin_vel_world_m_s[5:-5]) ** 2)) < 0.01
    dR = np.gradient(base.world_R_base, data.t_s, axis=0)
    skew = np.einsum("nij,nkj->nik", dR, base.world_R_base)  # dR R^T = [omega]x (world frame)
    omega = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1)
    assert np.sqrt(np.mean((omega[5:-5] - base.ang_vel_world_rad_s[5:-5]) ** 2)) < 0.02
    # the IMU reads gravity in the base frame while the trunk is level
    assert np.mean(data.accel_m_s2[:, 2]) == pytest.approx(9.81, abs=0.3)
