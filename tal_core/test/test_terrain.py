"""Tests of tal_core.terrain and tal_core.terrain_patches: presets, patch surfaces, queries, primitives."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from tal_core.course_io import shipped_course_names
from tal_core.errors import InputError
from tal_core.terrain import (
    MIN_BOX_THICKNESS_M,
    TERRAIN_PRESETS,
    Box,
    Course,
    SlopePatch,
    TerrainProperties,
    load_course,
    rotation_from_rpy,
)

TAN_15 = math.tan(math.radians(15.0))
SIN_15 = math.sin(math.radians(15.0))
COS_15 = math.cos(math.radians(15.0))


def write_course(
    tmp_path: Path,
    patches: list[dict],
    extent_x: tuple[float, float] = (-2.0, 8.0),
    default: dict | None = None,
) -> Course:
    """Write a course YAML with the given patches to tmp_path and load it."""
    document = {
        "course": {
            "name": "test_course",
            "extent": {"x": list(extent_x), "y": [-2.0, 2.0]},
            "default": default or {"terrain": "T4", "friction": 1.0, "height_m": 0.0},
            "patches": patches,
        }
    }
    path = tmp_path / "course.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return load_course(path)


@pytest.fixture
def all_types_course(tmp_path: Path) -> Course:
    """One patch of every type, some not spanning the full width, so the default ground is fragmented."""
    return write_course(
        tmp_path,
        [
            {"name": "ramp", "type": "slope", "x": [0.0, 1.0], "angle_deg": 15.0, "terrain": "T3"},
            {
                "name": "steps",
                "type": "stairs",
                "x": [1.0, 2.0],
                "y": [-1.0, 1.0],
                "rise_m": 0.1,
                "go_m": 0.3,
                "count": 3,
                "direction": "up",
                "start_height_m": TAN_15,
                "terrain": "T4",
            },
            {"name": "hole", "type": "gap", "x": [2.5, 3.0], "depth_m": 0.5, "terrain": "T4"},
            {
                "name": "cobbles",
                "type": "rough",
                "x": [3.0, 4.0],
                "y": [0.0, 1.05],
                "amplitude_m": 0.05,
                "cell_size_m": 0.1,
                "seed": 7,
                "terrain": "T2",
            },
            {
                "name": "raised",
                "type": "flat",
                "x": [5.0, 6.0],
                "y": [-2.0, -1.0],
                "height_m": 0.2,
                "terrain": "T1",
                "friction": 0.6,
            },
        ],
    )


class TestPresets:
    def test_thesis_values(self) -> None:
        assert {name: (p.stiffness_n_per_m, p.damping_ns_per_m) for name, p in TERRAIN_PRESETS.items()} == {
            "T1": (3500.0, 400.0),
            "T2": (8000.0, 400.0),
            "T3": (10000.0, 400.0),
            "T4": (2.0e6, 400.0),
        }

    def test_presets_are_read_only(self) -> None:
        with pytest.raises(TypeError):
            TERRAIN_PRESETS["T5"] = TERRAIN_PRESETS["T1"]  # type: ignore[index]


class TestPatchSurfaces:
    def test_slope_height_and_normal(self) -> None:
        course = load_course("slope_15deg")
        assert course.height(2.0, 0.3) == pytest.approx(TAN_15 * 1.0, abs=1e-12)  # 1 m up the ramp
        assert course.height(3.5, 0.0) == pytest.approx(2.0 * TAN_15, abs=1e-12)  # plateau
        assert course.height(5.0, 0.0) == pytest.approx(TAN_15 * 1.0, abs=1e-12)  # 1 m down the descent
        np.testing.assert_allclose(course.normal(2.0, 0.0), [-SIN_15, 0.0, COS_15], atol=1e-12)
        np.testing.assert_allclose(course.normal(5.0, 0.0), [SIN_15, 0.0, COS_15], atol=1e-12)
        np.testing.assert_allclose(course.normal(3.5, 0.0), [0.0, 0.0, 1.0])

    def test_slope_is_continuous_at_its_ends(self) -> None:
        course = load_course("slope_15deg")
        for x_joint in (1.0, 3.0, 4.0, 6.0):
            below, above = course.height([x_joint - 1e-9, x_joint + 1e-9], [0.0, 0.0])
            assert above == pytest.approx(below, abs=1e-8)

    def test_stairs_height_of_each_tread(self) -> None:
        course = load_course("stairs")
        tread_middles = 1.0 + 0.3 * np.arange(5) + 0.15
        np.testing.assert_allclose(course.height(tread_middles, 0.0), [0.1, 0.2, 0.3, 0.4, 0.5], atol=1e-12)
        assert course.height(0.99, 0.0) == 0.0  # before the first riser
        assert course.height(3.0, 0.0) == 0.5  # plateau
        down_middles = 3.5 + 0.3 * np.arange(5) + 0.15
        np.testing.assert_allclose(course.height(down_middles, 0.0), [0.4, 0.3, 0.2, 0.1, 0.0], atol=1e-12)
        np.testing.assert_allclose(course.normal(1.2, 0.5), [0.0, 0.0, 1.0])

    def test_stairs_last_tread_stays_flat_to_x_max(self) -> None:
        course = load_course("mixed_course")  # stairs_up: 5 steps from x 6.0, patch to 8.5
        np.testing.assert_allclose(course.height([7.6, 8.0, 8.49], 0.0), [0.5, 0.5, 0.5])

    def test_gap_floor(self, all_types_course: Course) -> None:
        assert all_types_course.height(2.75, 1.9) == pytest.approx(-0.5)
        assert all_types_course.patch_at(2.75, 1.9) == "hole"

    def test_rough_is_piecewise_constant_and_seeded(self, all_types_course: Course) -> None:
        cobbles = all_types_course.patch("cobbles")
        expected_first = np.random.default_rng(7).uniform(0.0, 0.05, size=(10, 11))[0, 0]
        same_stone = all_types_course.height([3.01, 3.09], [0.01, 0.09])
        assert same_stone[0] == same_stone[1] == pytest.approx(expected_first, abs=1e-15)
        assert cobbles.grid_shape == (10, 11)  # 1.05 m of y: the last row of stones is clipped
        heights = cobbles.stone_heights_m
        assert heights.min() >= 0.0 and heights.max() <= 0.05 and np.unique(heights).size == heights.size
        np.testing.assert_allclose(all_types_course.normal(3.5, 0.5), [0.0, 0.0, 1.0])

    def test_rough_same_seed_same_stones(self, tmp_path: Path, all_types_course: Course) -> None:
        again = write_course(
            tmp_path,
            [
                {
                    "name": "cobbles",
                    "type": "rough",
                    "x": [3.0, 4.0],
                    "y": [0.0, 1.05],
                    "amplitude_m": 0.05,
                    "cell_size_m": 0.1,
                    "seed": 7,
                    "terrain": "T2",
                }
            ],
        )
        np.testing.assert_array_equal(
            again.patch("cobbles").stone_heights_m, all_types_course.patch("cobbles").stone_heights_m
        )


class TestQueries:
    def test_outside_extent_is_nan(self) -> None:
        course = load_course("flat_rigid")
        assert math.isnan(course.height(-2.1, 0.0))
        assert np.all(np.isnan(course.normal(0.0, 2.5)))
        assert course.patch_at(20.0, 0.0) == "outside"

    def test_extent_is_closed_and_patches_half_open(self) -> None:
        course = load_course("stance_course")
        assert course.height(10.0, 2.0) == 0.0  # the extent's upper corner still has ground
        assert course.patch_at(2.0, 0.0) == "soft_t1"  # shared edges belong to the patch that starts there
        assert course.patch_at(4.0, 0.0) == "moderate_t2"
        assert course.patch_at(1.999, 0.0) == "default"

    def test_vectorised_shapes(self, all_types_course: Course) -> None:
        x = np.linspace(-1.0, 7.0, 20).reshape(4, 5)
        assert all_types_course.height(x, 0.5).shape == (4, 5)
        normals = all_types_course.normal(x, 0.5)
        assert normals.shape == (4, 5, 3)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0)
        assert all_types_course.patch_at(x, 0.5).shape == (4, 5)
        assert isinstance(all_types_course.height(0.5, 0.5), float)

    def test_bad_query_input(self, all_types_course: Course) -> None:
        with pytest.raises(InputError, match="broadcastable"):
            all_types_course.height(np.zeros(3), np.zeros(4))
        with pytest.raises(InputError, match="numeric"):
            all_types_course.height("a", 0.0)

    def test_properties_at_a_point(self) -> None:
        course = load_course("mixed_course")
        assert course.properties(2.0, 0.0) == TerrainProperties(3500.0, 400.0, 0.8, "soft_t1")
        assert course.properties(4.0, -1.0) == TerrainProperties(8000.0, 400.0, 0.9, "moderate_t2")
        assert course.properties(0.0, 0.0) == TerrainProperties(2.0e6, 400.0, 1.0, "default")

    def test_properties_errors(self) -> None:
        course = load_course("mixed_course")
        with pytest.raises(InputError, match=r"outside course 'mixed_course' extent"):
            course.properties(-3.0, 0.0)
        with pytest.raises(InputError, match="one finite point"):
            course.properties(float("nan"), 0.0)

    def test_properties_array(self) -> None:
        course = load_course("stance_course")
        stiffness, damping, friction = course.properties_array([0.0, 3.0, 5.0, 7.0, 9.0, 11.0], 0.0)
        np.testing.assert_array_equal(stiffness[:5], [2.0e6, 3500.0, 8000.0, 10000.0, 2.0e6])
        np.testing.assert_array_equal(damping[:5], 400.0)
        np.testing.assert_array_equal(friction[:5], 1.0)
        assert math.isnan(stiffness[5]) and math.isnan(friction[5])

    def test_explicit_stiffness_and_default_height(self, tmp_path: Path) -> None:
        course = write_course(
            tmp_path,
            [
                {
                    "name": "mud",
                    "type": "flat",
                    "x": [0.0, 1.0],
                    "stiffness_n_per_m": 1500.0,
                    "damping_ns_per_m": 250.0,
                }
            ],
            default={"terrain": "T3", "height_m": 0.3},
        )
        assert course.properties(0.5, 0.0) == TerrainProperties(1500.0, 250.0, 1.0, "mud")
        assert course.patch("mud").terrain is None
        assert course.height(0.5, 0.0) == 0.3  # flat height_m defaults to the default ground height
        with pytest.raises(InputError, match="has no patch 'bog'"):
            course.patch("bog")


def top_surfaces(boxes: list[Box], x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n_boxes, n_points) top-face z of each box above each point, NaN where not under the top face."""
    return np.stack([box.top_z(x, y) for box in boxes])


class TestPrimitives:
    @pytest.mark.parametrize("name", ["stance_course", "slope_15deg", "stairs", "mixed_course"])
    def test_exactly_one_top_surface_equals_height_shipped(self, name: str) -> None:
        self.check_top_surfaces(load_course(name))

    def test_exactly_one_top_surface_equals_height_all_types(self, all_types_course: Course) -> None:
        self.check_top_surfaces(all_types_course)

    @staticmethod
    def check_top_surfaces(course: Course) -> None:
        rng = np.random.default_rng(0)
        x = rng.uniform(course.extent.x_min, course.extent.x_max, 1500)
        y = rng.uniform(course.extent.y_min, course.extent.y_max, 1500)
        tops = top_surfaces(course.primitives(), x, y)
        covering = np.sum(~np.isnan(tops), axis=0)
        np.testing.assert_array_equal(covering, 1)
        np.testing.assert_allclose(np.nanmax(tops, axis=0), course.height(x, y), atol=1e-9, rtol=0)

    def test_contact_properties_follow_the_patch(self, all_types_course: Course) -> None:
        rng = np.random.default_rng(1)
        x, y = rng.uniform(-2.0, 8.0, 500), rng.uniform(-2.0, 2.0, 500)
        boxes = all_types_course.primitives()
        owner = np.nanargmax(np.nan_to_num(top_surfaces(boxes, x, y), nan=-np.inf), axis=0)
        stiffness, damping, friction = all_types_course.properties_array(x, y)
        np.testing.assert_array_equal([boxes[i].stiffness_n_per_m for i in owner], stiffness)
        np.testing.assert_array_equal([boxes[i].friction for i in owner], friction)

    def test_boxes_are_thick_and_share_a_floor(self, all_types_course: Course) -> None:
        boxes = all_types_course.primitives()
        floor = -0.5 - MIN_BOX_THICKNESS_M  # gap floor is the lowest surface
        for box in boxes:
            assert 2.0 * box.half_extents_xyz[2] >= MIN_BOX_THICKNESS_M - 1e-12, box.name
            if box.rpy == (0.0, 0.0, 0.0):
                assert box.center_xyz[2] - box.half_extents_xyz[2] == pytest.approx(floor, abs=1e-12)

    def test_slope_is_one_pitched_box(self) -> None:
        ramp = [b for b in load_course("slope_15deg").primitives() if b.name == "ramp_up"]
        assert len(ramp) == 1
        assert ramp[0].rpy == pytest.approx((0.0, -math.radians(15.0), 0.0))
        assert ramp[0].half_extents_xyz == pytest.approx((1.0 / COS_15, 2.0, MIN_BOX_THICKNESS_M / 2.0))
        world_R_box = rotation_from_rpy(*ramp[0].rpy)
        np.testing.assert_allclose(world_R_box[:, 2], [-SIN_15, 0.0, COS_15], atol=1e-12)  # box z = normal
        assert ramp[0].top_z(2.0, 0.0) == pytest.approx(TAN_15)

    def test_box_names_and_counts(self, all_types_course: Course) -> None:
        names = [b.name for b in all_types_course.primitives()]
        assert names.count("ramp") == 1 and "hole_floor" in names
        assert [n for n in names if n.startswith("steps_step")] == [
            "steps_step0",
            "steps_step1",
            "steps_step2",
        ]
        assert sum(n.startswith("cobbles_stone") for n in names) == 110
        assert len(set(names)) == len(names)

    def test_default_ground_merges_cells_along_x(self) -> None:
        boxes = load_course("stance_course").primitives()
        default = [b for b in boxes if b.name.startswith("default_")]
        assert [(b.center_xyz[0], b.half_extents_xyz[0]) for b in default] == [(0.0, 2.0), (9.0, 1.0)]

    def test_rotation_convention_matches_urdf(self) -> None:
        np.testing.assert_allclose(
            rotation_from_rpy(0.0, 0.0, math.pi / 2) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15
        )
        pitched = rotation_from_rpy(0.0, -0.3, 0.0) @ [1.0, 0.0, 0.0]  # negative pitch raises the x axis
        np.testing.assert_allclose(pitched, [math.cos(0.3), 0.0, math.sin(0.3)], atol=1e-15)

    def test_bad_thickness(self) -> None:
        with pytest.raises(InputError, match="min_thickness_m"):
            load_course("flat_rigid").primitives(min_thickness_m=0.0)


class TestShippedCourses:
    def test_all_shipped_courses_load(self) -> None:
        names = shipped_course_names()
        assert names == sorted(
            [
                "flat_foam",
                "flat_rigid",
                "flat_t1",
                "flat_t2",
                "flat_t3",
                "flat_t4",
                "stance_course",
                "slope_15deg",
                "stairs",
                "mixed_course",
                "trot_loop",
                "vital_stairs",
                "vital_gap_stairs",
                "vital_rough",
                "graph_tour",
            ]
        )
        for name in names:
            course = load_course(name)
            assert course.name == name
            if name == "trot_loop":  # a square around the origin, not a strip along x
                continue
            assert (course.extent.x_min, course.extent.y_min, course.extent.y_max) == (-2.0, -2.0, 2.0)
            last_patch_end = max([p.region.x_max for p in course.patches], default=course.extent.x_min)
            assert course.extent.x_max >= last_patch_end + 2.0

    def test_the_trot_loop_crosses_its_blocks_in_order_on_a_2_m_circle(self) -> None:
        course = load_course("trot_loop")
        angles = np.linspace(-np.pi / 2, 3 * np.pi / 2, 721)  # from the start (0, -2), counter-clockwise
        names = [str(course.patch_at(2.0 * np.cos(a), 2.0 * np.sin(a))) for a in angles]
        crossed = [n for i, n in enumerate(names) if i == 0 or n != names[i - 1]]
        assert crossed == ["default", "soft_t1", "default", "foam", "default", "moderate_t2", "default"]
        assert course.properties(0.0, 2.0).stiffness_n_per_m == 2400.0

    @pytest.mark.parametrize("terrain", ["T1", "T2", "T3", "T4"])
    def test_flat_courses_have_one_terrain(self, terrain: str) -> None:
        course = load_course(f"flat_{terrain.lower()}")
        stiffness, _, _ = course.properties_array(np.linspace(-2.0, 10.0, 50), 0.0)
        np.testing.assert_array_equal(stiffness, TERRAIN_PRESETS[terrain].stiffness_n_per_m)

    def test_stance_course_strips(self) -> None:
        course = load_course("stance_course.yaml")
        assert [course.patch_at(x, 0.0) for x in (1.0, 3.0, 5.0, 7.0, 9.0)] == [
            "default",
            "soft_t1",
            "moderate_t2",
            "stiff_t3",
            "default",
        ]

    def test_slope_patch_type(self) -> None:
        assert isinstance(load_course("slope_15deg").patch("ramp_up"), SlopePatch)


def test_height_and_properties_equal_the_separate_queries() -> None:
    """One look-up for both (the simulator's per-step power-law ground query), on every shipped course."""
    rng = np.random.default_rng(0)
    for name in shipped_course_names():
        course = load_course(name)
        ext = course.extent
        x = rng.uniform(ext.x_min - 0.5, ext.x_max + 0.5, 200)
        y = rng.uniform(ext.y_min - 0.5, ext.y_max + 0.5, 200)
        z, props = course.height_and_properties(x, y)
        np.testing.assert_array_equal(z, course.height(x, y))
        for got, expected in zip(props, course.properties_array(x, y)):
            np.testing.assert_array_equal(got, expected)
