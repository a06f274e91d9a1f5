"""Terrain-Based Body Reference (TBR), the thesis' baseline for the VPA (Villarreal et al. 2019).

The TBR fits a plane through the footholds selected by the VFA, takes its orientation as the body's
roll and pitch, and puts the base a constant distance above the plane's centre. Plane:
z = s_x x + s_y y + c in the horizontal frame (least squares; exact through 3 points, the best fit
through 4). With the Cardan angles of ``tal_msgs/BodyPoseReference`` (R = Rz(yaw) Ry(pitch) Rx(roll))
the body z axis is the plane normal (-s_x, -s_y, 1) / norm when pitch = -atan(s_x) and
roll = atan(s_y cos(pitch)). The base origin is the footholds' centroid on the plane plus
``height_m`` along the normal; its world z is the reference height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_perception.errors import PerceptionInputError, VpaConfigError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class TbrResult:
    """base_height_m [m] world z of the base origin; roll_rad, pitch_rad [rad]; plane_slopes (2,)
    [-] dz/dx, dz/dy in the horizontal frame; plane_centre (3,) [m] world."""

    base_height_m: float
    roll_rad: float
    pitch_rad: float
    plane_slopes: FloatArray
    plane_centre: FloatArray

    @property
    def pose(self) -> FloatArray:
        return np.array([self.base_height_m, self.roll_rad, self.pitch_rad])


class TerrainBasedReference:
    """TBR with the base ``height_m`` [m] above the footholds' plane (thesis: a constant distance)."""

    def __init__(self, height_m: float) -> None:
        if not (isinstance(height_m, (int, float, np.floating)) and math.isfinite(height_m) and height_m > 0.0):
            raise VpaConfigError(f"TBR height_m must be a finite value > 0 [m], got {height_m!r}")
        self.height_m = float(height_m)

    def reference(self, footholds_world: ArrayLike, yaw: float) -> TbrResult:
        """Pose reference from the selected footholds (n >= 3, 3) [m] world and the base yaw [rad]."""
        points = np.asarray(footholds_world, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 3:
            raise PerceptionInputError(f"TBR: footholds must have shape (n >= 3, 3) [m], got {points.shape}")
        if not np.isfinite(points).all():
            raise PerceptionInputError("TBR: footholds have non-finite values")
        if not math.isfinite(yaw):
            raise PerceptionInputError(f"TBR: yaw must be finite [rad], got {yaw!r}")
        centre = points.mean(axis=0)
        c, s = math.cos(yaw), math.sin(yaw)
        d = points[:, :2] - centre[:2]
        forward, left = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]  # world -> horizontal frame
        design = np.column_stack([forward, left, np.ones(len(points))])
        solution, _, rank, _ = np.linalg.lstsq(design, points[:, 2], rcond=None)
        if rank < 3:
            raise PerceptionInputError("TBR: the footholds are collinear, no plane through them")
        slope_x, slope_y, offset = (float(v) for v in solution)
        pitch = -math.atan(slope_x)
        roll = math.atan(slope_y * math.cos(pitch))
        normal = np.array([-slope_x, -slope_y, 1.0]) / math.sqrt(1.0 + slope_x**2 + slope_y**2)
        plane_centre = np.array([centre[0], centre[1], offset])
        height = offset + self.height_m * normal[2]
        return TbrResult(float(height), roll, pitch, np.array([slope_x, slope_y]), plane_centre)
