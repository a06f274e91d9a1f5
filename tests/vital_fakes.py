"""A synthetic wbc for the ViTAL node tests: the gait state of a HyQ trotting along +x and heightmaps of a
flat ground (optionally with a gap)."""

from __future__ import annotations

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point

from tal_core.heightmap import extract_heightmap
from tal_core.robot_model import RobotModel
from tal_core.ros.node_utils import stamp_from_ns
from tal_core.terrain import Course, DefaultGround, GapPatch, Region
from tal_msgs.msg import FootholdArray, GaitState, HeightMap

MS = 1_000_000  # [ns]
RIGID = {"stiffness_n_per_m": 2e6, "damping_ns_per_m": 400.0}
SPEED = 0.3  # [m/s]
FREQUENCY, DUTY = 1.5, 0.6  # trot: swing 0.267 s, stance 0.4 s


class FakeWbc:
    """Publishes the gait state of a HyQ trotting at SPEED along +x (LF and RH swinging) and heightmaps;
    records footholds and diagnostics."""

    def __init__(self, context) -> None:
        self.node = rclpy.create_node("fake_wbc", context=context)
        model = RobotModel(RobotModel.from_name("hyq").description)
        self.base_z = model.nominal_base_height_m
        model.update(model.neutral_q(self.base_z), np.zeros(model.nv))
        self.hips = model.hip_positions()  # (4, 3) [m] world, base at (0, 0) at t = 1 s
        self.gait = self.node.create_publisher(GaitState, "gait_state", 10)
        self.maps = self.node.create_publisher(HeightMap, "terrain/heightmap", 10)
        self.footholds: list[FootholdArray] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.node.create_subscription(FootholdArray, "footholds", self.footholds.append, 10)
        self.node.create_subscription(DiagnosticArray, "vfa/diagnostics", self.diagnostics.append, 10)

    def matched(self) -> bool:
        return (self.gait.get_subscription_count() >= 1 and self.maps.get_subscription_count() >= 1
                and self.node.count_publishers("footholds") >= 1)

    def nominal(self, leg: int) -> np.ndarray:
        """[m] Raibert nominal foothold of ``leg``'s current swing (constant over the swing)."""
        return self.hips[leg] + np.array([SPEED * (0.2 + 0.5 * DUTY / FREQUENCY), 0.0, -self.hips[leg, 2]])

    def gait_state(self, stamp_ns: int) -> GaitState:
        """The swing started at 0.9333 s, touchdown at 1.2 s; the base moves at SPEED."""
        t = stamp_ns * 1e-9
        msg = GaitState()
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.header.frame_id = "world"
        msg.gait, msg.step_frequency, msg.duty_factor, msg.step_height = "trot", FREQUENCY, DUTY, 0.1
        msg.swing_duration = (1.0 - DUTY) / FREQUENCY
        msg.base_twist.linear.x = SPEED
        for leg in range(4):
            swinging = leg in (0, 3)
            hip = self.hips[leg] + np.array([SPEED * (t - 1.0), 0.0, 0.0])
            nominal = self.nominal(leg)
            msg.swing[leg] = swinging
            msg.time_to_touchdown[leg] = max(1.2 - t, 0.0) if swinging else 0.0
            msg.step_count[leg] = 3
            msg.hip_position[leg] = Point(x=hip[0], y=hip[1], z=hip[2])
            msg.nominal_foothold[leg] = Point(x=nominal[0], y=nominal[1], z=nominal[2])
            msg.liftoff_position[leg] = Point(x=nominal[0] - SPEED / FREQUENCY, y=nominal[1], z=0.02175)
        return msg

    def heightmap(self, stamp_ns: int, gap_at_x: float | None = None, cells: int = 121) -> HeightMap:
        patches = () if gap_at_x is None else (GapPatch(name="gap", region=Region(gap_at_x - 0.06, gap_at_x + 0.06,
                                                                                 -3, 3), depth_m=0.3,
                                                        start_height_m=0.0, **RIGID),)
        course = Course("test", Region(-3, 3, -3, 3), DefaultGround(height_m=0.0, **RIGID), patches)
        grid = extract_heightmap(course, (SPEED * (stamp_ns * 1e-9 - 1.0), 0.0), 0.0, cells, cells, 0.02)
        msg = HeightMap(yaw=0.0, resolution=0.02, rows=cells, cols=cells, heights=grid.heights.ravel().tolist())
        msg.header.stamp = stamp_from_ns(stamp_ns)
        msg.header.frame_id = "world"
        msg.center.x, msg.center.y = grid.center_xy
        return msg
