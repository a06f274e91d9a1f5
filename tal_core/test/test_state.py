"""tal_core.state: the base state predicted forward at constant velocity."""

from __future__ import annotations

import numpy as np

from tal_core.rotations import quat_xyzw_from_rotation, rotation_from_quat_xyzw, so3_exp
from tal_core.state import BaseState


def test_a_base_state_predicted_forward_moves_and_turns_at_its_velocities() -> None:
    rotation = so3_exp(np.array([0.1, -0.2, 0.7]))
    omega = np.array([0.3, -0.1, 0.5])          # [rad/s] world frame
    base = BaseState(np.array([1.0, 2.0, 0.6]), quat_xyzw_from_rotation(rotation), np.array([0.2, -0.1, 0.05]), omega)
    later = base.predicted(0.02)
    np.testing.assert_allclose(later.position, [1.004, 1.998, 0.601], atol=1e-12)
    # Turned about the world-frame axis omega by |omega| dt.
    np.testing.assert_allclose(rotation_from_quat_xyzw(later.quat_xyzw), so3_exp(omega * 0.02) @ rotation, atol=1e-12)
    np.testing.assert_array_equal(later.linear_velocity, base.linear_velocity)
    np.testing.assert_array_equal(later.angular_velocity, base.angular_velocity)
    same = base.predicted(0.0)
    np.testing.assert_allclose(same.position, base.position, atol=0)
    np.testing.assert_allclose(rotation_from_quat_xyzw(same.quat_xyzw), rotation, atol=1e-12)
