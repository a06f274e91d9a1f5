"""Terrain patch types and collision boxes (world frame, SI units).

Each patch is a frozen dataclass that knows its surface height, normal and the collision boxes that
build it. Regions are half-open, [x_min, x_max) x [y_min, y_max), so a point on an edge shared by two
patches belongs to exactly one of them. ``terrain`` (the course) composes these; ``course_io`` builds
them from YAML.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from types import MappingProxyType
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ContactParameters:
    """Kelvin-Voigt ground parameters per contact point: stiffness [N/m] and damping [N s/m]."""

    stiffness_n_per_m: float
    damping_ns_per_m: float


TERRAIN_PRESETS: Mapping[str, ContactParameters] = MappingProxyType(
    {
        "T1": ContactParameters(3500.0, 400.0),  # soft
        "T2": ContactParameters(8000.0, 400.0),  # moderate
        "T3": ContactParameters(10000.0, 400.0),  # stiff
        "T4": ContactParameters(2.0e6, 400.0),  # rigid
    }
)
"""The thesis' terrain types (STANCE chapter), by name."""


@dataclass(frozen=True, kw_only=True)
class GroundContact:
    """Contact properties shared by patches and the default ground; terrain is the preset name if any."""

    stiffness_n_per_m: float
    damping_ns_per_m: float
    friction: float = 1.0
    terrain: str | None = None


@dataclass(frozen=True, kw_only=True)
class DefaultGround(GroundContact):
    """Ground inside the extent but outside every patch: flat at height_m [m] (world z)."""

    height_m: float = 0.0


@dataclass(frozen=True)
class Region:
    """Axis-aligned world-frame rectangle [x_min, x_max) x [y_min, y_max) [m]."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float

    @property
    def length_x_m(self) -> float:
        return self.x_max - self.x_min

    @property
    def width_y_m(self) -> float:
        return self.y_max - self.y_min

    def contains(self, x: FloatArray, y: FloatArray) -> NDArray[np.bool_]:
        """True where (x, y) [m] lies in the half-open rectangle."""
        return (x >= self.x_min) & (x < self.x_max) & (y >= self.y_min) & (y < self.y_max)

    def overlaps(self, other: Region) -> bool:
        """True if the two rectangles share a positive area (touching edges do not overlap)."""
        return (
            self.x_min < other.x_max
            and other.x_min < self.x_max
            and self.y_min < other.y_max
            and other.y_min < self.y_max
        )


def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> FloatArray:
    """world_R_body for fixed-axis roll, pitch, yaw [rad]: R = Rz(yaw) Ry(pitch) Rx(roll) (URDF, PyBullet)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


@dataclass(frozen=True)
class Box:
    """A static collision box for a physics engine.

    center_xyz [m] is the box centre in the world frame; rpy [rad] its orientation (fixed-axis roll,
    pitch, yaw, see ``rotation_from_rpy``); half_extents_xyz [m] are along the box's own axes. The top
    face is the walking surface. Contact: stiffness [N/m], damping [N s/m] per contact point, friction [-].
    """

    name: str
    center_xyz: tuple[float, float, float]
    half_extents_xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    stiffness_n_per_m: float
    damping_ns_per_m: float
    friction: float

    def top_z(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """World z [m] of the box's upward face above (x, y) [m]; NaN where (x, y) is not under that face."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        world_R_box = rotation_from_rpy(*self.rpy)
        center = np.asarray(self.center_xyz)
        half = np.asarray(self.half_extents_xyz)
        axis = int(np.argmax(np.abs(world_R_box[2])))  # the box axis closest to world z
        normal = world_R_box[:, axis] * np.sign(world_R_box[2, axis])
        face_center = center + normal * half[axis]
        z = face_center[2] - (normal[0] * (x - face_center[0]) + normal[1] * (y - face_center[1])) / normal[2]
        points = np.stack([x, y, z], axis=-1) - center
        local = points @ world_R_box  # rows are box-frame coordinates
        tolerance = 1e-12
        inside = np.all(np.abs(local) <= half + tolerance, axis=-1)
        return np.where(inside, z, np.nan)


def axis_aligned_box(
    name: str,
    ground: GroundContact,
    x: tuple[float, float],
    y: tuple[float, float],
    top_z: float,
    bottom_z: float,
) -> Box:
    """A box spanning x, y [m] from bottom_z up to top_z [m] (world frame), with the ground's contact."""
    return Box(
        name=name,
        center_xyz=(0.5 * (x[0] + x[1]), 0.5 * (y[0] + y[1]), 0.5 * (top_z + bottom_z)),
        half_extents_xyz=(0.5 * (x[1] - x[0]), 0.5 * (y[1] - y[0]), 0.5 * (top_z - bottom_z)),
        rpy=(0.0, 0.0, 0.0),
        stiffness_n_per_m=ground.stiffness_n_per_m,
        damping_ns_per_m=ground.damping_ns_per_m,
        friction=ground.friction,
    )


def _vertical_normals(x: FloatArray) -> FloatArray:
    normals = np.zeros(x.shape + (3,))
    normals[..., 2] = 1.0
    return normals


@dataclass(frozen=True, kw_only=True)
class Patch(GroundContact):
    """Base of all patch types. ``kind`` is the YAML ``type``; region is in the world frame."""

    kind: ClassVar[str] = ""
    name: str
    region: Region

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Surface z [m] (world) at points (x, y) [m] that lie in the region."""
        raise NotImplementedError

    def normal(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Unit surface normals (..., 3), world frame; vertical faces are ignored (top surface normal)."""
        return _vertical_normals(x)

    def lowest_z(self) -> float:
        """Lowest surface z [m] in the patch, used to put a common floor under all boxes."""
        raise NotImplementedError

    def boxes(self, bottom_z: float, thickness_m: float) -> list[Box]:
        """Collision boxes whose top faces form this patch's surface, solid down to bottom_z [m]."""
        raise NotImplementedError

    def _span_x(self) -> tuple[float, float]:
        return (self.region.x_min, self.region.x_max)

    def _span_y(self) -> tuple[float, float]:
        return (self.region.y_min, self.region.y_max)


@dataclass(frozen=True, kw_only=True)
class FlatPatch(Patch):
    """Horizontal ground with its top surface at height_m [m] (world z)."""

    kind: ClassVar[str] = "flat"
    height_m: float

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return np.full(np.shape(x), self.height_m)

    def lowest_z(self) -> float:
        return self.height_m

    def boxes(self, bottom_z: float, thickness_m: float) -> list[Box]:
        return [axis_aligned_box(self.name, self, self._span_x(), self._span_y(), self.height_m, bottom_z)]


@dataclass(frozen=True, kw_only=True)
class SlopePatch(Patch):
    """A ramp rising along world +x by angle_deg [deg] (negative: descending) from start_height_m at x_min."""

    kind: ClassVar[str] = "slope"
    angle_deg: float
    start_height_m: float

    @property
    def end_height_m(self) -> float:
        """Surface z [m] at x_max."""
        return self.start_height_m + math.tan(math.radians(self.angle_deg)) * self.region.length_x_m

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return self.start_height_m + math.tan(math.radians(self.angle_deg)) * (x - self.region.x_min)

    def normal(self, x: FloatArray, y: FloatArray) -> FloatArray:
        angle = math.radians(self.angle_deg)
        return np.broadcast_to(np.array([-math.sin(angle), 0.0, math.cos(angle)]), np.shape(x) + (3,)).copy()

    def lowest_z(self) -> float:
        return min(self.start_height_m, self.end_height_m)

    def boxes(self, bottom_z: float, thickness_m: float) -> list[Box]:
        # One box pitched by -angle (its x axis rises along world +x), thickness_m measured along the
        # surface normal. Its end faces are perpendicular to the slope, so below the surface they reach
        # thickness_m * sin|angle| past x_min or x_max, under the higher neighbour.
        angle = math.radians(self.angle_deg)
        normal = np.array([-math.sin(angle), 0.0, math.cos(angle)])
        top_middle = np.array(
            [
                0.5 * (self.region.x_min + self.region.x_max),
                0.5 * (self.region.y_min + self.region.y_max),
                0.5 * (self.start_height_m + self.end_height_m),
            ]
        )
        center = top_middle - normal * 0.5 * thickness_m
        half_extents = (
            0.5 * self.region.length_x_m / math.cos(angle),
            0.5 * self.region.width_y_m,
            0.5 * thickness_m,
        )
        return [
            Box(
                name=self.name,
                center_xyz=tuple(float(v) for v in center),
                half_extents_xyz=half_extents,
                rpy=(0.0, -angle, 0.0),
                stiffness_n_per_m=self.stiffness_n_per_m,
                damping_ns_per_m=self.damping_ns_per_m,
                friction=self.friction,
            )
        ]


@dataclass(frozen=True, kw_only=True)
class StairsPatch(Patch):
    """count steps of rise_m [m] and go_m [m] along +x; the first riser stands at x_min.

    Tread i (0-based) spans [x_min + i go, x_min + (i + 1) go) at start_height_m + s (i + 1) rise_m with
    s = +1 for direction "up" and -1 for "down"; the last tread stays flat to x_max.
    """

    kind: ClassVar[str] = "stairs"
    rise_m: float
    go_m: float
    count: int
    direction: str
    start_height_m: float

    @property
    def tread_heights_m(self) -> FloatArray:
        """Surface z [m] of each tread, first to last."""
        sign = 1.0 if self.direction == "up" else -1.0
        return self.start_height_m + sign * self.rise_m * np.arange(1, self.count + 1)

    def tread_index(self, x: FloatArray) -> NDArray[np.intp]:
        """Index of the tread under world x [m] (points past the last riser are on the last tread)."""
        index = np.floor((x - self.region.x_min) / self.go_m)
        return np.clip(index, 0, self.count - 1).astype(np.intp)

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return self.tread_heights_m[self.tread_index(x)]

    def lowest_z(self) -> float:
        return float(self.tread_heights_m.min())

    def boxes(self, bottom_z: float, thickness_m: float) -> list[Box]:
        boxes = []
        for i, top in enumerate(self.tread_heights_m):
            x_start = self.region.x_min + i * self.go_m
            x_end = self.region.x_max if i == self.count - 1 else self.region.x_min + (i + 1) * self.go_m
            boxes.append(
                axis_aligned_box(
                    f"{self.name}_step{i}", self, (x_start, x_end), self._span_y(), float(top), bottom_z
                )
            )
        return boxes


@dataclass(frozen=True, kw_only=True)
class GapPatch(Patch):
    """A hole over the whole region whose floor is depth_m [m] below start_height_m [m]."""

    kind: ClassVar[str] = "gap"
    depth_m: float
    start_height_m: float

    @property
    def floor_height_m(self) -> float:
        return self.start_height_m - self.depth_m

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return np.full(np.shape(x), self.floor_height_m)

    def lowest_z(self) -> float:
        return self.floor_height_m

    def boxes(self, bottom_z: float, thickness_m: float) -> list[Box]:
        return [
            axis_aligned_box(
                f"{self.name}_floor", self, self._span_x(), self._span_y(), self.floor_height_m, bottom_z
            )
        ]


@dataclass(frozen=True, kw_only=True)
class RoughPatch(Patch):
    """Cobblestones: square stones of cell_size_m [m] on a grid anchored at (x_min, y_min).

    Each stone's top is base_height_m + U(0, amplitude_m) [m], drawn with numpy's default_rng(seed) in
    (ix, iy) order, so a course is the same on every machine. Stones on the far edges are clipped.
    """

    kind: ClassVar[str] = "rough"
    amplitude_m: float
    cell_size_m: float
    seed: int
    base_height_m: float

    @property
    def grid_shape(self) -> tuple[int, int]:
        """Number of stones along x and y."""
        return (
            math.ceil(self.region.length_x_m / self.cell_size_m - 1e-9),
            math.ceil(self.region.width_y_m / self.cell_size_m - 1e-9),
        )

    @cached_property
    def stone_heights_m(self) -> FloatArray:
        """Top z [m] of each stone, shape grid_shape, read-only."""
        offsets = np.random.default_rng(self.seed).uniform(0.0, self.amplitude_m, size=self.grid_shape)
        heights = self.base_height_m + offsets
        heights.setflags(write=False)
        return heights

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        n_x, n_y = self.grid_shape
        ix = np.clip(np.floor((x - self.region.x_min) / self.cell_size_m), 0, n_x - 1).astype(np.intp)
        iy = np.clip(np.floor((y - self.region.y_min) / self.cell_size_m), 0, n_y - 1).astype(np.intp)
        return self.stone_heights_m[ix, iy]

    def lowest_z(self) -> float:
        return float(self.stone_heights_m.min())

    def boxes(self, bottom_z: float, thickness_m: float) -> list[Box]:
        n_x, n_y = self.grid_shape
        x_edges = np.minimum(self.region.x_min + self.cell_size_m * np.arange(n_x + 1), self.region.x_max)
        y_edges = np.minimum(self.region.y_min + self.cell_size_m * np.arange(n_y + 1), self.region.y_max)
        boxes = []
        for ix in range(n_x):
            x_span = (float(x_edges[ix]), float(x_edges[ix + 1]))
            for iy in range(n_y):
                y_span = (float(y_edges[iy]), float(y_edges[iy + 1]))
                boxes.append(
                    axis_aligned_box(
                        f"{self.name}_stone{ix}_{iy}",
                        self,
                        x_span,
                        y_span,
                        float(self.stone_heights_m[ix, iy]),
                        bottom_z,
                    )
                )
        return boxes


PATCH_TYPES: Mapping[str, type[Patch]] = MappingProxyType(
    {cls.kind: cls for cls in (FlatPatch, SlopePatch, StairsPatch, GapPatch, RoughPatch)}
)
"""Patch classes by YAML ``type``."""
