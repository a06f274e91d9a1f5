"""The estimation nodes' serialised outputs carry what they are given, in the frames the messages say."""

from __future__ import annotations

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message

from tal_core.rotations import rotation_from_quat_xyzw
from tal_estimation.messages import EstimateWriters

GYRO_VARIANCE = 1e-4


def test_odometry_pose_in_world_twist_in_base_and_covariances() -> None:
    rng = np.random.default_rng(1)
    quat = rng.normal(size=4)
    world_R_base = rotation_from_quat_xyzw(quat / np.linalg.norm(quat))
    position, velocity, omega = rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
    p_cov, v_cov, a_cov = (np.diag(rng.random(3)) for _ in range(3))
    writers = EstimateWriters(GYRO_VARIANCE)
    writers.odometry(1, np.zeros(3), np.eye(3), np.ones(3), np.ones(3), np.eye(3), np.eye(3), np.eye(3))  # reused
    msg = deserialize_message(writers.odometry(2_003_000_000, position, world_R_base, velocity, omega, p_cov, v_cov,
                                               a_cov), Odometry)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (2, 3_000_000)
    assert (msg.header.frame_id, msg.child_frame_id) == ("world", "base")
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z], position)
    np.testing.assert_allclose(rotation_from_quat_xyzw(np.array([q.x, q.y, q.z, q.w])), world_R_base, atol=1e-12)
    t = msg.twist.twist
    np.testing.assert_allclose([t.linear.x, t.linear.y, t.linear.z], world_R_base.T @ velocity)
    np.testing.assert_allclose([t.angular.x, t.angular.y, t.angular.z], omega)
    pose_cov = np.array(msg.pose.covariance).reshape(6, 6)
    np.testing.assert_allclose(pose_cov[:3, :3], p_cov)
    np.testing.assert_allclose(pose_cov[3:, 3:], a_cov)
    np.testing.assert_allclose(pose_cov[:3, 3:], 0.0)
    twist_cov = np.array(msg.twist.covariance).reshape(6, 6)
    np.testing.assert_allclose(twist_cov[:3, :3], world_R_base.T @ v_cov @ world_R_base)
    np.testing.assert_allclose(twist_cov[3:, 3:], np.eye(3) * GYRO_VARIANCE)
