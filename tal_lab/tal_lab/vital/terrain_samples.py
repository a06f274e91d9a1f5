"""Seeded random terrains as heightmap patches (flat, bars, gaps, stairs, rocks), for FEC labels.

Each sample is a small ``tal_core.terrain.Course`` (the same patch types the simulator builds) sampled
by ``tal_core.heightmap.extract_heightmap`` on a patch-sized grid centred at the origin with a random
heading, so features cross the patch at any angle. The same seed gives the same samples on every
machine (numpy's default_rng).

Units: metres, world frame; the patch follows the ``tal_msgs/HeightMap`` cell convention.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tal_core.heightmap import extract_heightmap
from tal_core.terrain import Course, DefaultGround, FlatPatch, GapPatch, Patch, Region, RoughPatch, StairsPatch
from tal_perception.errors import FecConfigError

TERRAIN_KINDS: tuple[str, ...] = ("flat", "bars", "gaps", "stairs", "rocks")
_HALF_EXTENT_M = 1.0  # [m] the course spans [-1, 1] m in x and y, larger than any patch diagonal
_MAX_SIZE_M = math.sqrt(2.0) * _HALF_EXTENT_M  # [m] edge of the largest patch whose corners stay on it
_RIGID = {"stiffness_n_per_m": 2.0e6, "damping_ns_per_m": 400.0}


@dataclass(frozen=True, eq=False)
class TerrainSample:
    """One random terrain patch: heights (cells, cells) float32 [m] world z, the kind, the yaw [rad]
    the grid was sampled at and the generating parameters (SI units)."""

    kind: str
    heights: NDArray[np.float32]
    resolution_m: float
    yaw: float
    parameters: dict[str, float] = field(default_factory=dict)


def _region(x_min: float, x_max: float) -> Region:
    return Region(x_min, x_max, -_HALF_EXTENT_M, _HALF_EXTENT_M)


def _patches(kind: str, rng: np.random.Generator, base_z: float) -> tuple[list[Patch], dict[str, float]]:
    """The random patches of one terrain kind (world frame, features along x)."""
    ground = dict(_RIGID, friction=1.0)
    if kind == "flat":
        return [], {}
    if kind == "bars":
        height, width, x0 = rng.uniform(0.03, 0.15), rng.uniform(0.04, 0.2), rng.uniform(-0.3, 0.2)
        bar = FlatPatch(name="bar", region=_region(x0, x0 + width), height_m=base_z + height, **ground)
        return [bar], {"bar_height_m": height, "bar_width_m": width, "bar_start_m": x0}
    if kind == "gaps":
        depth, width, x0 = rng.uniform(0.1, 0.5), rng.uniform(0.04, 0.25), rng.uniform(-0.3, 0.2)
        gap = GapPatch(name="gap", region=_region(x0, x0 + width), depth_m=depth, start_height_m=base_z, **ground)
        return [gap], {"gap_depth_m": depth, "gap_width_m": width, "gap_start_m": x0}
    if kind == "stairs":
        rise, go, x0 = rng.uniform(0.05, 0.18), rng.uniform(0.2, 0.35), rng.uniform(-0.4, 0.1)
        direction = "up" if rng.uniform() < 0.5 else "down"
        stairs = StairsPatch(
            name="stairs", region=_region(x0, _HALF_EXTENT_M), rise_m=rise, go_m=go, count=4,
            direction=direction, start_height_m=base_z, **ground,
        )  # fmt: skip
        return [stairs], {"rise_m": rise, "go_m": go, "stairs_start_m": x0, "up": float(direction == "up")}
    if kind == "rocks":
        amplitude, cell = rng.uniform(0.02, 0.12), rng.uniform(0.06, 0.2)
        rocks = RoughPatch(
            name="rocks", region=Region(-_HALF_EXTENT_M, _HALF_EXTENT_M, -_HALF_EXTENT_M, _HALF_EXTENT_M),
            amplitude_m=amplitude, cell_size_m=cell, seed=int(rng.integers(2**31)), base_height_m=base_z, **ground,
        )  # fmt: skip
        return [rocks], {"amplitude_m": amplitude, "stone_size_m": cell}
    raise FecConfigError(f"terrain kind {kind!r} is not one of {', '.join(TERRAIN_KINDS)}")


def random_terrain(
    rng: np.random.Generator, kind: str | None = None, cells: int = 33, resolution_m: float = 0.02
) -> TerrainSample:
    """One random patch of ``kind`` (random kind if None) with ``cells`` x ``cells`` cells."""
    if isinstance(cells, bool) or not isinstance(cells, int) or cells < 1:
        raise FecConfigError(f"cells must be an integer >= 1, got {cells!r}")
    if not (math.isfinite(resolution_m) and 0.0 < resolution_m and cells * resolution_m < _MAX_SIZE_M):
        raise FecConfigError(
            f"resolution_m must be > 0 with cells * resolution_m < {_MAX_SIZE_M:.3f} m (the patch, at any "
            f"heading, must stay on the {2 * _HALF_EXTENT_M} m course), got {cells} x {resolution_m!r}"
        )
    kind = TERRAIN_KINDS[int(rng.integers(len(TERRAIN_KINDS)))] if kind is None else kind
    base_z = float(rng.uniform(-0.2, 0.2))
    patches, parameters = _patches(kind, rng, base_z)
    course = Course(
        name=f"sample_{kind}",
        extent=Region(-_HALF_EXTENT_M, _HALF_EXTENT_M, -_HALF_EXTENT_M, _HALF_EXTENT_M),
        default=DefaultGround(height_m=base_z, **_RIGID),
        patches=tuple(patches),
    )
    yaw = float(rng.uniform(-math.pi, math.pi))
    grid = extract_heightmap(course, (0.0, 0.0), yaw, cells, cells, resolution_m)
    return TerrainSample(kind, grid.heights, resolution_m, yaw, {"base_height_m": base_z, **parameters})


def terrain_samples(
    seed: int, count: int, kinds: tuple[str, ...] = TERRAIN_KINDS, cells: int = 33, resolution_m: float = 0.02
) -> Iterator[TerrainSample]:
    """``count`` samples cycling through ``kinds``, reproducible from ``seed``."""
    unknown = [k for k in kinds if k not in TERRAIN_KINDS]
    if unknown or not kinds:
        raise FecConfigError(f"kinds must be a non-empty subset of {', '.join(TERRAIN_KINDS)}, got {kinds!r}")
    rng = np.random.default_rng(seed)
    for i in range(count):
        yield random_terrain(rng, kinds[i % len(kinds)], cells, resolution_m)
