"""Message conversions of the estimation nodes, shared with the offline replay of their topics (a bag)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import JointState

from tal_core.errors import InputError
from tal_core.ros.conversions import canonical_joint_state

from .streaming import JointArrays


def joint_state_arrays(msg: JointState, index: dict[str, int]) -> JointArrays:
    """Positions [rad], velocities [rad/s] and efforts (measured torques) [N m] of a joint state in canonical
    order; InputError when a joint is unknown or missing, a length differs from the names' or a value is not
    finite."""
    q, qd = canonical_joint_state(msg, index)
    if len(msg.effort) != len(msg.name):
        raise InputError(f"joint_states has {len(msg.name)} names and {len(msg.effort)} efforts")
    tau = np.full(len(index), np.nan)
    for name, effort in zip(msg.name, msg.effort):
        tau[index[name]] = effort
    if not np.all(np.isfinite(tau)):
        raise InputError("joint_states efforts have NaN/inf")
    return q, qd, tau
