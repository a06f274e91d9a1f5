"""joint_state_arrays and foot_contact_values: what the estimator node reads from its input messages."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Vector3
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_estimation.messages import foot_contact_values, joint_state_arrays
from tal_msgs.msg import ContactState

NAMES = [f"j{i}" for i in range(12)]
INDEX = {name: i for i, name in enumerate(NAMES)}


def message(velocity: bool = True, effort: bool = True) -> JointState:
    return JointState(name=NAMES, position=[0.1 * i for i in range(12)],
                      velocity=[0.2] * 12 if velocity else [], effort=[3.0] * 12 if effort else [])


@pytest.mark.parametrize("velocity, effort, match", [(False, True, "12 names, 12 positions and 0 velocities"),
                                                     (True, False, "12 names and 0 efforts")])
def test_missing_arrays_are_rejected_by_default(velocity: bool, effort: bool, match: str) -> None:
    with pytest.raises(InputError, match=match):
        joint_state_arrays(message(velocity, effort), INDEX)


def test_missing_arrays_give_none_when_optional() -> None:
    q, qd, tau = joint_state_arrays(message(False, False), INDEX, velocities_optional=True, efforts_optional=True)
    np.testing.assert_allclose(q, [0.1 * i for i in range(12)])
    assert qd is None and tau is None
    q, qd, tau = joint_state_arrays(message(), INDEX, velocities_optional=True, efforts_optional=True)
    np.testing.assert_allclose(qd, 0.2) and np.testing.assert_allclose(tau, 3.0)
    with pytest.raises(InputError, match="0 positions"):  # positions are never optional
        joint_state_arrays(JointState(name=NAMES), INDEX, velocities_optional=True, efforts_optional=True)


def test_foot_contact_values_per_source() -> None:
    msg = ContactState(in_contact=[True, False, True, False],
                       force=[Vector3(x=0.0, y=0.0, z=f) for f in (100.0, 0.0, 250.0, 3.0)])
    np.testing.assert_allclose(foot_contact_values(msg, "force_sensor"), [100.0, 0.0, 250.0, 3.0])
    np.testing.assert_allclose(foot_contact_values(msg, "contact_flags"), [1.0, 0.0, 1.0, 0.0])
    with pytest.raises(InputError, match="reads no foot contact"):
        foot_contact_values(msg, "torque")
