"""Terrain courses: ground patches with height, normal and contact properties (world frame).

A course is a world-frame rectangle (the extent) of default ground carrying non-overlapping patches:
flat, slope, stairs, gap and rough (cobblestones). Every query is vectorised over numpy arrays and also
accepts scalars. Courses are read from YAML by ``load_course`` (parsing lives in ``course_io``);
robot-centric heightmaps live in ``heightmap``.

Conventions: world frame, z up, SI units. Patch regions are half-open, [x_min, x_max) x [y_min, y_max),
so a point on an edge shared by two patches belongs to exactly one of them. The extent itself is closed:
points on its upper edges are nudged one ulp inside before the patch look-up.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tal_core.errors import InputError
from tal_core.terrain_patches import (
    PATCH_TYPES,
    TERRAIN_PRESETS,
    Box,
    ContactParameters,
    DefaultGround,
    FlatPatch,
    GapPatch,
    GroundContact,
    Patch,
    Region,
    RoughPatch,
    SlopePatch,
    StairsPatch,
    axis_aligned_box,
    rotation_from_rpy,
)

__all__ = [
    "DEFAULT_PATCH_NAME",
    "MIN_BOX_THICKNESS_M",
    "OUTSIDE_PATCH_NAME",
    "PATCH_TYPES",
    "TERRAIN_PRESETS",
    "Box",
    "ContactParameters",
    "Course",
    "DefaultGround",
    "FlatPatch",
    "GapPatch",
    "GroundContact",
    "Patch",
    "Region",
    "RoughPatch",
    "SlopePatch",
    "StairsPatch",
    "TerrainProperties",
    "TerrainPropertyArrays",
    "load_course",
    "rotation_from_rpy",
]

FloatArray = NDArray[np.float64]

DEFAULT_PATCH_NAME = "default"
"""Name reported for ground that lies inside the extent but on no patch."""
OUTSIDE_PATCH_NAME = "outside"
"""Name reported for points outside the course extent (there is no ground there)."""
# [m] Thick enough that a foot sunk into the softest ground (T1: 6 cm standing, > 30 cm under dynamic
# loads on three legs) stays closer to the top face than to the bottom one: Bullet pushes a sphere out
# through the nearest face, so a thin box would pull a deeply sunk foot down.
MIN_BOX_THICKNESS_M = 1.0
"""Minimum thickness [m] of every collision box below its top surface."""

_OUTSIDE_INDEX = -2
_DEFAULT_INDEX = -1
_LOOKUP_OFFSET = 2  # maps the patch index (-2 outside, -1 default, 0.. patches) onto table rows


@dataclass(frozen=True)
class TerrainProperties:
    """Contact properties of the ground at one point: stiffness [N/m], damping [N s/m], friction [-]."""

    stiffness_n_per_m: float
    damping_ns_per_m: float
    friction: float
    patch: str  # name of the patch the point lies on, or DEFAULT_PATCH_NAME


class TerrainPropertyArrays(NamedTuple):
    """Vectorised contact properties, each with the broadcast shape of the query (NaN outside)."""

    stiffness_n_per_m: FloatArray
    damping_ns_per_m: FloatArray
    friction: FloatArray


def _as_points(x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray, bool]:
    """Broadcast query coordinates [m] to float arrays; the flag says whether both were scalars."""
    try:
        x_array, y_array = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    except (TypeError, ValueError) as error:
        raise InputError(f"terrain query needs numeric x, y of broadcastable shapes: {error}") from None
    return x_array, y_array, x_array.ndim == 0


@dataclass(frozen=True)
class Course:
    """A terrain course: default ground over the extent plus non-overlapping patches (world frame).

    Build it with ``load_course``; the constructor trusts its inputs (validation happens at load time).
    """

    name: str
    extent: Region
    default: DefaultGround
    patches: tuple[Patch, ...] = ()
    source: str = "<memory>"

    def patch(self, name: str) -> Patch:
        """The patch called ``name``; raises InputError if there is none."""
        for patch in self.patches:
            if patch.name == name:
                return patch
        raise InputError(
            f"course '{self.name}' has no patch '{name}'; patches: "
            f"{', '.join(p.name for p in self.patches) or 'none'}"
        )

    def _locate(self, x: FloatArray, y: FloatArray) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
        """Patch index per point (-2 outside the extent, -1 default ground) and the nudged coordinates."""
        ext = self.extent
        inside = (x >= ext.x_min) & (x <= ext.x_max) & (y >= ext.y_min) & (y <= ext.y_max)
        # The extent is closed but patches are half-open: move points on the upper edges just inside.
        x = np.where(x == ext.x_max, np.nextafter(ext.x_max, -np.inf), x)
        y = np.where(y == ext.y_max, np.nextafter(ext.y_max, -np.inf), y)
        index = np.where(inside, _DEFAULT_INDEX, _OUTSIDE_INDEX).astype(np.intp)
        for i, patch in enumerate(self.patches):
            index[inside & patch.region.contains(x, y)] = i
        return index, x, y

    def height(self, x: ArrayLike, y: ArrayLike) -> FloatArray | float:
        """Ground surface z [m] (world) at (x, y) [m]; NaN outside the extent. Shape: broadcast of x, y."""
        x, y, scalar = _as_points(x, y)
        z = self._height_at(*self._locate(x, y))
        return float(z) if scalar else z

    def height_and_properties(self, x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, TerrainPropertyArrays]:
        """``height`` and ``properties_array`` at (x, y) [m] with one patch look-up (the simulator's
        per-step query for a power-law ground)."""
        x, y, _ = _as_points(x, y)
        index, x, y = self._locate(x, y)
        return self._height_at(index, x, y), self._properties_at(index)

    def _height_at(self, index: NDArray[np.intp], x: FloatArray, y: FloatArray) -> FloatArray:
        z = np.full(x.shape, np.nan)
        z[index == _DEFAULT_INDEX] = self.default.height_m
        for i, patch in enumerate(self.patches):
            on_patch = index == i
            if on_patch.any():
                z[on_patch] = patch.height(x[on_patch], y[on_patch])
        return z

    def normal(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Unit ground normals (..., 3) in the world frame at (x, y) [m]; NaN outside the extent.

        Normals come from the analytic top surface: vertical faces of steps and stones are ignored.
        """
        x, y, _ = _as_points(x, y)
        index, x, y = self._locate(x, y)
        normals = np.full(x.shape + (3,), np.nan)
        normals[index == _DEFAULT_INDEX] = (0.0, 0.0, 1.0)
        for i, patch in enumerate(self.patches):
            on_patch = index == i
            if on_patch.any():
                normals[on_patch] = patch.normal(x[on_patch], y[on_patch])
        return normals

    def _grounds(self) -> tuple[GroundContact, ...]:
        """Default ground then patches, in look-up table order."""
        return (self.default, *self.patches)

    def properties_array(self, x: ArrayLike, y: ArrayLike) -> TerrainPropertyArrays:
        """Stiffness [N/m], damping [N s/m], friction [-] at (x, y) [m]; NaN outside the extent."""
        x, y, _ = _as_points(x, y)
        return self._properties_at(self._locate(x, y)[0])

    def _properties_at(self, index: NDArray[np.intp]) -> TerrainPropertyArrays:
        rows = index + _LOOKUP_OFFSET

        def table(attribute: str) -> FloatArray:
            return np.array([np.nan] + [getattr(g, attribute) for g in self._grounds()])[rows]

        return TerrainPropertyArrays(table("stiffness_n_per_m"), table("damping_ns_per_m"), table("friction"))

    def patch_at(self, x: ArrayLike, y: ArrayLike) -> str | NDArray[np.object_]:
        """Name of the patch at (x, y) [m]: a patch name, "default" or "outside" (array for array input)."""
        x, y, scalar = _as_points(x, y)
        index, _, _ = self._locate(x, y)
        all_names = [OUTSIDE_PATCH_NAME, DEFAULT_PATCH_NAME, *(p.name for p in self.patches)]
        names = np.array(all_names, dtype=object)
        found = names[index + _LOOKUP_OFFSET]
        return str(found) if scalar else found

    def properties(self, x: float, y: float) -> TerrainProperties:
        """Contact properties at one point (x, y) [m]; raises InputError outside the extent or for NaN."""
        x_array, y_array, scalar = _as_points(x, y)
        if not scalar or not (np.isfinite(x_array) and np.isfinite(y_array)):
            raise InputError(
                f"properties() needs one finite point, got x={x!r}, y={y!r}; "
                "use properties_array() for arrays"
            )
        index = int(self._locate(x_array, y_array)[0])
        if index == _OUTSIDE_INDEX:
            ext = self.extent
            raise InputError(
                f"point ({x}, {y}) m is outside course '{self.name}' extent "
                f"x [{ext.x_min}, {ext.x_max}], y [{ext.y_min}, {ext.y_max}]"
            )
        ground = self._grounds()[index + 1]
        name = DEFAULT_PATCH_NAME if index == _DEFAULT_INDEX else self.patches[index].name
        return TerrainProperties(ground.stiffness_n_per_m, ground.damping_ns_per_m, ground.friction, name)

    def primitives(self, min_thickness_m: float = MIN_BOX_THICKNESS_M) -> list[Box]:
        """Collision boxes for a physics engine: default ground first, then each patch in order.

        Axis-aligned boxes reach down to a common floor, min_thickness_m [m] below the lowest surface of
        the course, so the ground is solid and gap walls have no holes; slope boxes are min_thickness_m
        thick along their normal. Above every point of the extent exactly one box has its top face, at
        ``height(x, y)``.
        """
        if not (math.isfinite(min_thickness_m) and min_thickness_m > 0.0):
            raise InputError(f"min_thickness_m must be a finite value > 0, got {min_thickness_m!r}")
        lowest = min([self.default.height_m] + [p.lowest_z() for p in self.patches])
        bottom_z = lowest - min_thickness_m
        boxes = self._default_ground_boxes(bottom_z)
        for patch in self.patches:
            boxes.extend(patch.boxes(bottom_z, min_thickness_m))
        return boxes

    def _default_ground_boxes(self, bottom_z: float) -> list[Box]:
        """Cover the extent minus the patches with boxes on the grid of all patch breakpoints.

        Cells uncovered by any patch are merged into runs along x within each y band.
        """
        regions = [p.region for p in self.patches]
        xs = sorted({coordinate for r in (self.extent, *regions) for coordinate in (r.x_min, r.x_max)})
        ys = sorted({coordinate for r in (self.extent, *regions) for coordinate in (r.y_min, r.y_max)})
        boxes: list[Box] = []
        for y_low, y_high in zip(ys[:-1], ys[1:], strict=True):
            run_start: float | None = None
            for x_low, x_high in zip(xs[:-1], xs[1:], strict=True):
                middle = (np.array(0.5 * (x_low + x_high)), np.array(0.5 * (y_low + y_high)))
                covered = any(bool(r.contains(*middle)) for r in regions)
                if not covered and run_start is None:
                    run_start = x_low
                elif covered and run_start is not None:
                    boxes.append(self._default_box(len(boxes), (run_start, x_low), (y_low, y_high), bottom_z))
                    run_start = None
            if run_start is not None:
                boxes.append(self._default_box(len(boxes), (run_start, xs[-1]), (y_low, y_high), bottom_z))
        return boxes

    def _default_box(
        self, number: int, x: tuple[float, float], y: tuple[float, float], bottom_z: float
    ) -> Box:
        return axis_aligned_box(
            f"{DEFAULT_PATCH_NAME}_{number}", self.default, x, y, self.default.height_m, bottom_z
        )


def load_course(path_or_name: str | os.PathLike[str]) -> Course:
    """Load a course from a YAML path or the name of a shipped course (see ``course_io.load_course``)."""
    from tal_core.course_io import load_course as load  # deferred: course_io builds the types above

    return load(path_or_name)
