"""Seeded whole-robot VPA scenes: a terrain course around the robot, its heightmap and a twist.

Each scene is a tal_core course (flat, bars, gaps, stairs or rocks; features across the walking
direction, starting 0-0.8 m ahead of the base), sampled as a robot-centric ``HeightMapGrid`` large
enough for all leg maps of both horizon stages (141 x 141 cells of 0.02 m), with the robot at the origin
heading along world x and a forward twist. Used by the accuracy protocol and the bench.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tal_core.heightmap import HeightMapGrid, extract_heightmap
from tal_core.terrain import Course, DefaultGround, FlatPatch, GapPatch, Patch, Region, RoughPatch, StairsPatch

SCENE_KINDS = ("flat", "bars", "gaps", "stairs", "rocks")
_EXTENT_M = 3.0  # [m] the course spans +-3 m
_MAP_CELLS = 141  # [-] robot map: 2.82 m, covers hips +- 0.37 m, the 0.47 m shift and half a leg map
_RIGID = {"stiffness_n_per_m": 2.0e6, "damping_ns_per_m": 400.0, "friction": 1.0}


@dataclass(frozen=True, eq=False)
class VpaScene:
    """kind; grid the robot's heightmap (world frame, centred on the base); base_position (3,) [m] with
    the base at the nominal height above the ground under it; twist (6,) [m/s, rad/s] horizontal frame."""

    kind: str
    grid: HeightMapGrid
    base_position: NDArray[np.float64]
    twist: NDArray[np.float64]


def _band(x0: float, x1: float) -> Region:
    return Region(x0, x1, -_EXTENT_M, _EXTENT_M)


def _patches(kind: str, rng: np.random.Generator) -> list[Patch]:
    x0 = float(rng.uniform(0.0, 0.8))
    if kind == "bars":
        height, width = rng.uniform(0.05, 0.15), rng.uniform(0.08, 0.25)
        return [FlatPatch(name="bar", region=_band(x0, x0 + width), height_m=height, **_RIGID)]
    if kind == "gaps":
        depth, width = rng.uniform(0.1, 0.5), rng.uniform(0.06, 0.25)
        return [GapPatch(name="gap", region=_band(x0, x0 + width), depth_m=depth, start_height_m=0.0, **_RIGID)]
    if kind == "stairs":
        rise, go = rng.uniform(0.06, 0.15), rng.uniform(0.22, 0.35)
        direction = "up" if rng.uniform() < 0.5 else "down"
        return [StairsPatch(name="stairs", region=_band(x0, _EXTENT_M), rise_m=rise, go_m=go, count=6,
                            direction=direction, start_height_m=0.0, **_RIGID)]  # fmt: skip
    if kind == "rocks":
        amplitude, cell = rng.uniform(0.02, 0.08), rng.uniform(0.08, 0.2)
        region = Region(-_EXTENT_M, _EXTENT_M, -_EXTENT_M, _EXTENT_M)
        return [RoughPatch(name="rocks", region=region, amplitude_m=amplitude, cell_size_m=cell,
                           seed=int(rng.integers(2**31)), base_height_m=0.0, **_RIGID)]  # fmt: skip
    return []


def vpa_scenes(seed: int, count: int, nominal_height_m: float) -> Iterator[VpaScene]:
    """``count`` scenes cycling through the kinds, reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    for i in range(count):
        kind = SCENE_KINDS[i % len(SCENE_KINDS)]
        course = Course(
            name=f"vpa_scene_{kind}", extent=Region(-_EXTENT_M, _EXTENT_M, -_EXTENT_M, _EXTENT_M),
            default=DefaultGround(height_m=0.0, stiffness_n_per_m=2.0e6, damping_ns_per_m=400.0),
            patches=tuple(_patches(kind, rng)),
        )  # fmt: skip
        grid = extract_heightmap(course, (0.0, 0.0), 0.0, _MAP_CELLS, _MAP_CELLS, 0.02)
        ground = float(course.height(np.array([0.0]), np.array([0.0]))[0])
        twist = np.array([rng.uniform(0.1, 0.4), rng.uniform(-0.05, 0.05), 0.0, 0.0, 0.0, rng.uniform(-0.2, 0.2)])
        yield VpaScene(kind, grid, np.array([0.0, 0.0, ground + nominal_height_m]), twist)
