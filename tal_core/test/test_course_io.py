"""Tests of tal_core.course_io: every validation case names the file, the patch and the field."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from tal_core.course_io import load_course, parse_course
from tal_core.errors import CourseConfigError

GOOD_PATCH: dict[str, Any] = {
    "name": "soft_t1",
    "type": "flat",
    "x": [1.0, 3.0],
    "terrain": "T1",
    "friction": 0.8,
}


def course_document(patch_list: Any, **overrides: Any) -> dict[str, Any]:
    """A course document with the given patches; overrides replace course-level fields."""
    course = {
        "name": "bad",
        "extent": {"x": [-2.0, 6.0], "y": [-2.0, 2.0]},
        "default": {"terrain": "T4", "friction": 1.0, "height_m": 0.0},
        "patches": patch_list,
    }
    course.update(overrides)
    return {"course": course}


def write(tmp_path: Path, document: Any) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def patch_with(**changes: Any) -> dict[str, Any]:
    """GOOD_PATCH with fields changed; a value of None removes the field."""
    patch = {**GOOD_PATCH, **changes}
    return {key: value for key, value in patch.items() if value is not None}


def test_error_message_names_file_patch_and_field(tmp_path: Path) -> None:
    path = write(
        tmp_path, course_document([patch_with(terrain=None, stiffness_n_per_m=-5, damping_ns_per_m=400)])
    )
    expected = f"{path}: patch 'soft_t1' (#0): field 'stiffness_n_per_m' must be > 0, got -5"
    with pytest.raises(CourseConfigError, match=f"^{re.escape(expected)}$"):
        load_course(path)


PATCH_CASES = [
    pytest.param(
        patch_with(type="hill"),
        r"field 'type' must be one of flat, slope, stairs, gap, rough, got 'hill'",
        id="unknown type",
    ),
    pytest.param(
        patch_with(heigth_m=0.1),
        r"field 'heigth_m' is unknown here; allowed fields: .*height_m",
        id="unknown field",
    ),
    pytest.param(patch_with(type="slope"), r"field 'angle_deg' is missing", id="missing field"),
    pytest.param(patch_with(x=None), r"field 'x' is missing", id="missing region"),
    pytest.param(
        patch_with(friction="high"), r"field 'friction' must be a number, got str 'high'", id="wrong type"
    ),
    pytest.param(
        patch_with(friction=True), r"field 'friction' must be a number, got bool", id="bool is no number"
    ),
    pytest.param(
        patch_with(terrain=None, stiffness_n_per_m=float("inf"), damping_ns_per_m=400),
        r"field 'stiffness_n_per_m' must be finite, got inf",
        id="infinite stiffness",
    ),
    pytest.param(
        patch_with(terrain=None, stiffness_n_per_m=float("nan"), damping_ns_per_m=400),
        r"field 'stiffness_n_per_m' must be finite, got nan",
        id="nan stiffness",
    ),
    pytest.param(
        patch_with(terrain=None, stiffness_n_per_m=0.0, damping_ns_per_m=400),
        r"field 'stiffness_n_per_m' must be > 0, got 0.0",
        id="zero stiffness",
    ),
    pytest.param(
        patch_with(terrain=None, stiffness_n_per_m=1000.0, damping_ns_per_m=-1.0),
        r"field 'damping_ns_per_m' must be >= 0, got -1.0",
        id="negative damping",
    ),
    pytest.param(
        patch_with(terrain=None, stiffness_n_per_m=1000.0),
        r"field 'damping_ns_per_m' is missing",
        id="stiffness without damping",
    ),
    pytest.param(patch_with(friction=0), r"field 'friction' must be > 0, got 0", id="zero friction"),
    pytest.param(
        patch_with(x=[3.0, 1.0]), r"field 'x' must have x_min < x_max, got \[3, 1\]", id="x reversed"
    ),
    pytest.param(patch_with(x=[1.0, 1.0]), r"field 'x' must have x_min < x_max", id="x empty"),
    pytest.param(
        patch_with(y=[0.5]), r"field 'y' must be a list \[min, max\] of two numbers", id="y malformed"
    ),
    pytest.param(
        patch_with(terrain="T9"),
        r"field 'terrain' must be one of T1, T2, T3, T4, got 'T9'",
        id="unknown preset",
    ),
    pytest.param(
        patch_with(stiffness_n_per_m=1000.0),
        r"field 'terrain' and 'stiffness_n_per_m'.* are exclusive",
        id="preset and stiffness",
    ),
    pytest.param(patch_with(terrain=None), r"field 'terrain' is missing", id="no contact properties"),
    pytest.param(
        patch_with(type="stairs", rise_m=0.1, go_m=0.3, count=8, direction="up"),
        r"field 'count' times go_m \(8 x 0.3 m\) exceeds the patch length 2 m",
        id="stairs too long",
    ),
    pytest.param(
        patch_with(type="stairs", rise_m=0.1, go_m=0.3, count=2.5, direction="up"),
        r"field 'count' must be an integer, got float 2.5",
        id="fractional count",
    ),
    pytest.param(
        patch_with(type="stairs", rise_m=0.1, go_m=0.3, count=2, direction="sideways"),
        r"field 'direction' must be one of up, down, got 'sideways'",
        id="bad direction",
    ),
    pytest.param(
        patch_with(type="slope", angle_deg=90),
        r"field 'angle_deg' must be in \(-90, 90\), got 90",
        id="vertical slope",
    ),
    pytest.param(
        patch_with(type="gap", depth_m=-0.2), r"field 'depth_m' must be > 0, got -0.2", id="gap depth"
    ),
    pytest.param(
        patch_with(type="rough", amplitude_m=0.05, cell_size_m=0.1, seed=-1),
        r"field 'seed' must be >= 0, got -1",
        id="negative seed",
    ),
    pytest.param(
        patch_with(type="rough", amplitude_m=0.05, cell_size_m=0.01, seed=1),
        r"field 'cell_size_m' gives 80000 stones; at most 10000 per patch",
        id="too many stones",
    ),
    pytest.param(
        patch_with(x=[5.0, 7.0]),
        r"field 'x' \[5, 7\] lies outside the extent x \[-2, 6\]",
        id="outside extent x",
    ),
    pytest.param(
        patch_with(y=[1.0, 3.0]),
        r"field 'y' \[1, 3\] lies outside the extent y \[-2, 2\]",
        id="outside extent y",
    ),
]


@pytest.mark.parametrize(("patch", "message"), PATCH_CASES)
def test_patch_validation(tmp_path: Path, patch: dict[str, Any], message: str) -> None:
    path = write(tmp_path, course_document([patch]))
    with pytest.raises(CourseConfigError, match=re.escape(f"{path}: patch 'soft_t1' (#0): ") + message):
        load_course(path)


def test_patch_without_name_is_named_by_index(tmp_path: Path) -> None:
    path = write(tmp_path, course_document([GOOD_PATCH, patch_with(name=None, x=[3.0, 4.0])]))
    with pytest.raises(CourseConfigError, match=re.escape(f"{path}: patch #1: field 'name' is missing")):
        load_course(path)


def test_reserved_patch_name(tmp_path: Path) -> None:
    path = write(tmp_path, course_document([patch_with(name="outside")]))
    with pytest.raises(
        CourseConfigError,
        match=r"patch 'outside' \(#0\): field 'name' must not be a reserved name "
        r"\(default, outside\), got 'outside'",
    ):
        load_course(path)


def test_overlapping_patches(tmp_path: Path) -> None:
    path = write(tmp_path, course_document([GOOD_PATCH, patch_with(name="t2", x=[2.5, 4.0], y=[0.0, 1.0])]))
    with pytest.raises(
        CourseConfigError,
        match=r"patch 't2' \(#1\): fields 'x'/'y': region x \[2.5, 4\] "
        r"y \[0, 1\] overlaps patch 'soft_t1' \(#0\)",
    ):
        load_course(path)


def test_touching_patches_do_not_overlap(tmp_path: Path) -> None:
    path = write(tmp_path, course_document([GOOD_PATCH, patch_with(name="t2", x=[3.0, 4.0], terrain="T2")]))
    assert [p.name for p in load_course(path).patches] == ["soft_t1", "t2"]


def test_duplicate_names(tmp_path: Path) -> None:
    path = write(tmp_path, course_document([GOOD_PATCH, patch_with(x=[3.0, 4.0])]))
    with pytest.raises(CourseConfigError, match=r"patch 'soft_t1' \(#1\): field 'name' repeats .* patch #0"):
        load_course(path)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            {"default": {"terrain": "T4", "friction": -1.0}},
            r"default: field 'friction' must be > 0, got -1.0",
        ),
        ({"default": {"terrain": "T4", "height": 0.0}}, r"default: field 'height' is unknown"),
        ({"extent": {"x": [6.0, -2.0], "y": [-2.0, 2.0]}}, r"extent: field 'x' must have x_min < x_max"),
        ({"extent": {"x": [-2.0, 6.0]}}, r"extent: field 'y' is missing"),
        ({"colour": "green"}, r"course: field 'colour' is unknown"),
        ({"name": 3}, r"course: field 'name' must be a non-empty string, got int 3"),
    ],
)
def test_course_level_validation(tmp_path: Path, overrides: dict[str, Any], message: str) -> None:
    path = write(tmp_path, course_document([], **overrides))
    with pytest.raises(CourseConfigError, match=re.escape(f"{path}: ") + message):
        load_course(path)


def test_patches_not_a_list(tmp_path: Path) -> None:
    path = write(tmp_path, course_document({"name": "p"}))
    with pytest.raises(CourseConfigError, match=re.escape(f"{path}: course: field 'patches' must be a list")):
        load_course(path)


def test_patch_not_a_mapping(tmp_path: Path) -> None:
    path = write(tmp_path, course_document(["flat"]))
    with pytest.raises(CourseConfigError, match=r"patch #0: expected a mapping of fields, got str"):
        load_course(path)


def test_file_problems(tmp_path: Path) -> None:
    broken = tmp_path / "broken.yaml"
    broken.write_text("course: {name: [unclosed", encoding="utf-8")
    with pytest.raises(CourseConfigError, match=r"broken.yaml: not valid YAML"):
        load_course(broken)
    empty = tmp_path / "empty.yaml"
    empty.write_text("", encoding="utf-8")
    with pytest.raises(CourseConfigError, match=r"empty.yaml: file is empty"):
        load_course(empty)
    with pytest.raises(CourseConfigError, match=r"expected exactly one top-level key 'course'"):
        parse_course({"track": {}}, "inline")
    with pytest.raises(CourseConfigError, match=r"no_such_course: no such course file.*shipped: .*stairs"):
        load_course("no_such_course")
    with pytest.raises(CourseConfigError, match=r"no such course file"):
        load_course(tmp_path / "missing.yaml")


def test_defaults_are_filled(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        course_document(
            [{"name": "ramp", "type": "slope", "x": [0.0, 1.0], "angle_deg": 10, "terrain": "T2"}],
            default={"terrain": "T4", "height_m": 0.25},
        ),
    )
    course = load_course(path)
    ramp = course.patch("ramp")
    assert (ramp.region.y_min, ramp.region.y_max) == (-2.0, 2.0)  # y defaults to the extent's width
    assert ramp.start_height_m == 0.25 and ramp.friction == 1.0 and ramp.terrain == "T2"
    assert course.default.friction == 1.0 and course.source == str(path)
