"""The bridge's byte writers publish exactly what its message functions build (the functions stay for bags)."""

from __future__ import annotations

import numpy as np
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock

from tal_core.ros.node_utils import stamp_from_ns
from tal_msgs.msg import ContactState
from tal_sim_bridge.physics import FootContact, RobotState
from tal_sim_bridge.sensor_messages import (
    SensorWriters,
    contact_state_message,
    imu_message,
    joint_state_message,
    odometry_message,
)

NAMES = [f"{leg}_{j}_joint" for leg in ("lf", "rf", "lh", "rh") for j in ("haa", "hfe", "kfe")]
STAMP_NS = 12_004_000_000


def _state(rng: np.random.Generator) -> RobotState:
    quat = rng.normal(size=4)
    return RobotState(rng.normal(size=3), quat / np.linalg.norm(quat), rng.normal(size=3), rng.normal(size=3),
                      rng.normal(size=3), rng.normal(size=12), rng.normal(size=12), rng.normal(size=12))


def test_writers_match_the_message_functions() -> None:
    rng = np.random.default_rng(3)
    writers = SensorWriters(NAMES, 0.01, 0.2)
    stamp = stamp_from_ns(STAMP_NS)
    for _ in range(3):  # the templates are reused: each sample overwrites all of the previous one
        state = _state(rng)
        f, w = rng.normal(size=3), rng.normal(size=3)
        contacts = [FootContact(bool(rng.integers(2)), rng.normal(size=3), float(rng.random()), rng.normal(size=3),
                                rng.normal(size=3), rng.normal(size=3)) for _ in range(4)]
        pairs = [(writers.joint_state(STAMP_NS, state), joint_state_message(stamp, NAMES, state)),
                 (writers.imu(STAMP_NS, f, w), imu_message(stamp, f, w, 0.01, 0.2)),
                 (writers.odometry(STAMP_NS, state), odometry_message(stamp, state)),
                 (writers.contact_state(STAMP_NS, contacts), contact_state_message(stamp, contacts))]
        for data, expected in pairs:
            got = deserialize_message(data, type(expected))
            if isinstance(expected, ContactState):  # float32-free, but bool arrays compare element-wise
                for field in ("in_contact", "probability", "penetration", "penetration_rate"):
                    np.testing.assert_array_equal(getattr(got, field), getattr(expected, field))
                for field in ("force", "foot_position", "foot_velocity", "normal"):
                    assert getattr(got, field) == getattr(expected, field), field
                assert got.header == expected.header
            else:
                assert got == expected, type(expected).__name__
    clock = deserialize_message(writers.clock(STAMP_NS), Clock)
    assert clock.clock == stamp
