"""Loading and validation of terrain course YAML files.

Format (world frame, SI units)::

    course:
      name: rigid_then_t1
      extent: {x: [-2.0, 6.0], y: [-2.0, 2.0]}    # the rectangle that has ground at all
      default: {terrain: T4, friction: 1.0, height_m: 0.0}    # ground outside every patch
      patches:
        - {name: soft_t1, type: flat, x: [1.0, 3.0], terrain: T1, friction: 0.8}

Every patch has ``name``, ``type``, ``x: [x_min, x_max]``, optional ``y`` (default: the extent's y),
either ``terrain`` (a preset T1..T4) or ``stiffness_n_per_m`` and ``damping_ns_per_m``, and ``friction``
(default 1.0). Heights of the type-specific fields (``height_m``, ``start_height_m``, ``base_height_m``)
default to the default ground's ``height_m``. Every error is a CourseConfigError naming the file, the
patch (name and index) and the field.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any, NoReturn

import yaml

from tal_core.errors import CourseConfigError
from tal_core.terrain import (
    DEFAULT_PATCH_NAME,
    OUTSIDE_PATCH_NAME,
    TERRAIN_PRESETS,
    Course,
    DefaultGround,
    FlatPatch,
    GapPatch,
    Patch,
    Region,
    RoughPatch,
    SlopePatch,
    StairsPatch,
)

_MISSING: Any = object()
_CONTACT_FIELDS = ("terrain", "stiffness_n_per_m", "damping_ns_per_m", "friction")
_COMMON_PATCH_FIELDS = ("name", "type", "x", "y", *_CONTACT_FIELDS)
_TYPE_FIELDS: Mapping[str, tuple[str, ...]] = {
    "flat": ("height_m",),
    "slope": ("angle_deg", "start_height_m"),
    "stairs": ("rise_m", "go_m", "count", "direction", "start_height_m"),
    "gap": ("depth_m", "start_height_m"),
    "rough": ("amplitude_m", "cell_size_m", "seed", "base_height_m"),
}
_RESERVED_NAMES = (DEFAULT_PATCH_NAME, OUTSIDE_PATCH_NAME)
MAX_STONES_PER_PATCH = 10_000
"""Upper bound on the stones of one rough patch (each is a collision box)."""


def shipped_course_names() -> list[str]:
    """Names (file stems) of the courses shipped in tal_core/config/courses, sorted."""
    folder = resources.files("tal_core") / "config" / "courses"
    return sorted(entry.name[: -len(".yaml")] for entry in folder.iterdir() if entry.name.endswith(".yaml"))


def load_course(path_or_name: str | os.PathLike[str]) -> Course:
    """Load and validate a course from a YAML file path, or the name of a shipped course.

    A name is a file stem of ``tal_core/config/courses`` (``"stance_course"`` or ``"stance_course.yaml"``).
    Raises CourseConfigError if the file is missing, unreadable, not YAML or invalid.
    """
    path = Path(path_or_name)
    if path.is_file():
        return _parse_text(_read_text(path), str(path))
    stem = path.name[: -len(".yaml")] if path.name.endswith(".yaml") else path.name
    if len(path.parts) == 1 and stem in shipped_course_names():
        shipped = resources.files("tal_core") / "config" / "courses" / f"{stem}.yaml"
        return _parse_text(shipped.read_text(encoding="utf-8"), str(shipped))
    raise CourseConfigError(
        f"{path_or_name}: no such course file, nor a shipped course "
        f"(shipped: {', '.join(shipped_course_names())})"
    )


def parse_course(data: Any, source: str = "<dict>") -> Course:
    """Validate already-parsed YAML data (the top-level mapping) into a Course; source names it in errors."""
    if data is None:
        raise CourseConfigError(f"{source}: file is empty; expected a top-level 'course' mapping")
    if not isinstance(data, Mapping) or set(data) != {"course"}:
        raise CourseConfigError(f"{source}: expected exactly one top-level key 'course'")
    course = _Fields(data["course"], f"{source}: course", ("name", "extent", "default", "patches"))
    name = course.string("name")
    extent_fields = _Fields(course.required("extent"), f"{source}: extent", ("x", "y"))
    x_min, x_max = extent_fields.interval("x")
    y_min, y_max = extent_fields.interval("y")
    extent = Region(x_min, x_max, y_min, y_max)
    default = _parse_default(
        _Fields(course.required("default"), f"{source}: default", (*_CONTACT_FIELDS, "height_m"))
    )
    patch_list = course.optional("patches", [])
    if not isinstance(patch_list, list):
        course.fail("patches", f"must be a list of patches, got {type(patch_list).__name__}")
    patches = tuple(_parse_patch(entry, i, source, extent, default) for i, entry in enumerate(patch_list))
    _check_layout(patches, extent, source)
    return Course(name=name, extent=extent, default=default, patches=patches, source=source)


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise CourseConfigError(f"{path}: cannot read course file: {error}") from None


def _parse_text(text: str, source: str) -> Course:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise CourseConfigError(f"{source}: not valid YAML: {error}") from None
    return parse_course(data, source)


class _Fields:
    """Reads typed fields from one YAML mapping; every error names ``where`` and the field."""

    def __init__(self, data: Any, where: str, allowed: tuple[str, ...] | None) -> None:
        """allowed: the known field names (others are an error); None skips that check."""
        self.where = where
        if not isinstance(data, Mapping):
            raise CourseConfigError(f"{where}: expected a mapping of fields, got {type(data).__name__}")
        self.data = data
        unknown = [key for key in data if allowed is not None and key not in allowed]
        if unknown:
            self.fail(str(unknown[0]), f"is unknown here; allowed fields: {', '.join(allowed or ())}")

    def fail(self, field: str, message: str) -> NoReturn:
        raise CourseConfigError(f"{self.where}: field '{field}' {message}")

    def has(self, field: str) -> bool:
        return field in self.data

    def required(self, field: str) -> Any:
        if field not in self.data:
            self.fail(field, "is missing")
        return self.data[field]

    def optional(self, field: str, default: Any) -> Any:
        return self.data.get(field, default)

    def number(
        self, field: str, default: Any = _MISSING, *, minimum: float | None = None, exclusive: bool = True
    ) -> float:
        """A finite number; with minimum, it must be > minimum (>= when exclusive is False)."""
        if default is not _MISSING and field not in self.data:
            return float(default)
        value = self.required(field)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(field, f"must be a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(value):
            self.fail(field, f"must be finite, got {value}")
        if minimum is not None and (value <= minimum if exclusive else value < minimum):
            self.fail(field, f"must be {'>' if exclusive else '>='} {minimum:g}, got {value}")
        return float(value)

    def integer(self, field: str, *, minimum: int) -> int:
        value = self.required(field)
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(field, f"must be an integer, got {type(value).__name__} {value!r}")
        if value < minimum:
            self.fail(field, f"must be >= {minimum}, got {value}")
        return int(value)

    def string(self, field: str, default: Any = _MISSING, choices: tuple[str, ...] | None = None) -> str:
        value = self.optional(field, default) if default is not _MISSING else self.required(field)
        if not isinstance(value, str) or not value:
            self.fail(field, f"must be a non-empty string, got {type(value).__name__} {value!r}")
        if choices is not None and value not in choices:
            self.fail(field, f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def interval(self, field: str, default: Any = _MISSING) -> tuple[float, float]:
        """A [min, max] pair of finite numbers [m] with min < max."""
        value = self.optional(field, default) if default is not _MISSING else self.required(field)
        if (
            not isinstance(value, (list, tuple))
            or len(value) != 2
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value)
        ):
            self.fail(field, f"must be a list [min, max] of two numbers, got {value!r}")
        low, high = float(value[0]), float(value[1])
        if not (math.isfinite(low) and math.isfinite(high)):
            self.fail(field, f"must be finite, got {value!r}")
        if low >= high:
            self.fail(field, f"must have {field}_min < {field}_max, got [{low:g}, {high:g}]")
        return low, high


def _parse_contact(fields: _Fields) -> dict[str, Any]:
    """Stiffness [N/m], damping [N s/m], friction [-] and preset name from a preset or explicit values."""
    explicit = fields.has("stiffness_n_per_m") or fields.has("damping_ns_per_m")
    if fields.has("terrain") and explicit:
        fields.fail("terrain", "and 'stiffness_n_per_m'/'damping_ns_per_m' are exclusive; give one of them")
    if fields.has("terrain"):
        preset = fields.string("terrain", choices=tuple(TERRAIN_PRESETS))
        stiffness = TERRAIN_PRESETS[preset].stiffness_n_per_m
        damping = TERRAIN_PRESETS[preset].damping_ns_per_m
    elif explicit:
        preset = None
        stiffness = fields.number("stiffness_n_per_m", minimum=0.0)
        damping = fields.number("damping_ns_per_m", minimum=0.0, exclusive=False)
    else:
        fields.fail(
            "terrain", "is missing (give a preset T1..T4, or 'stiffness_n_per_m' and 'damping_ns_per_m')"
        )
    friction = fields.number("friction", 1.0, minimum=0.0)
    return {
        "stiffness_n_per_m": stiffness,
        "damping_ns_per_m": damping,
        "friction": friction,
        "terrain": preset,
    }


def _parse_default(fields: _Fields) -> DefaultGround:
    return DefaultGround(height_m=fields.number("height_m", 0.0), **_parse_contact(fields))


def _patch_where(entry: Any, index: int, source: str) -> str:
    name = entry.get("name") if isinstance(entry, Mapping) else None
    return f"{source}: patch '{name}' (#{index})" if isinstance(name, str) else f"{source}: patch #{index}"


def _parse_patch(entry: Any, index: int, source: str, extent: Region, default: DefaultGround) -> Patch:
    """One patch of the list; index is its 0-based position, used in error messages."""
    where = _patch_where(entry, index, source)
    kind = _Fields(entry, where, allowed=None).string("type", choices=tuple(_TYPE_FIELDS))
    fields = _Fields(entry, where, (*_COMMON_PATCH_FIELDS, *_TYPE_FIELDS[kind]))
    name = fields.string("name")
    if name in _RESERVED_NAMES:
        fields.fail("name", f"must not be a reserved name ({', '.join(_RESERVED_NAMES)}), got {name!r}")
    x_min, x_max = fields.interval("x")
    y_min, y_max = fields.interval("y", [extent.y_min, extent.y_max])
    common = {"name": name, "region": Region(x_min, x_max, y_min, y_max), **_parse_contact(fields)}
    return _TYPE_PARSERS[kind](fields, common, default.height_m)


def _parse_flat(fields: _Fields, common: dict[str, Any], default_height_m: float) -> Patch:
    return FlatPatch(height_m=fields.number("height_m", default_height_m), **common)


def _parse_slope(fields: _Fields, common: dict[str, Any], default_height_m: float) -> Patch:
    angle_deg = fields.number("angle_deg")
    if not abs(angle_deg) < 90.0:
        fields.fail("angle_deg", f"must be in (-90, 90), got {angle_deg:g}")
    return SlopePatch(
        angle_deg=angle_deg, start_height_m=fields.number("start_height_m", default_height_m), **common
    )


def _parse_stairs(fields: _Fields, common: dict[str, Any], default_height_m: float) -> Patch:
    go_m = fields.number("go_m", minimum=0.0)
    count = fields.integer("count", minimum=1)
    length_m = common["region"].length_x_m
    if count * go_m > length_m + 1e-9:
        fields.fail("count", f"times go_m ({count} x {go_m:g} m) exceeds the patch length {length_m:g} m")
    return StairsPatch(
        rise_m=fields.number("rise_m", minimum=0.0),
        go_m=go_m,
        count=count,
        direction=fields.string("direction", choices=("up", "down")),
        start_height_m=fields.number("start_height_m", default_height_m),
        **common,
    )


def _parse_gap(fields: _Fields, common: dict[str, Any], default_height_m: float) -> Patch:
    return GapPatch(
        depth_m=fields.number("depth_m", minimum=0.0),
        start_height_m=fields.number("start_height_m", default_height_m),
        **common,
    )


def _parse_rough(fields: _Fields, common: dict[str, Any], default_height_m: float) -> Patch:
    patch = RoughPatch(
        amplitude_m=fields.number("amplitude_m", minimum=0.0, exclusive=False),
        cell_size_m=fields.number("cell_size_m", minimum=0.0),
        seed=fields.integer("seed", minimum=0),
        base_height_m=fields.number("base_height_m", default_height_m),
        **common,
    )
    stones = patch.grid_shape[0] * patch.grid_shape[1]
    if stones > MAX_STONES_PER_PATCH:  # every stone becomes one collision body in the simulator
        fields.fail("cell_size_m", f"gives {stones} stones; at most {MAX_STONES_PER_PATCH} per patch")
    return patch


_TYPE_PARSERS = {
    "flat": _parse_flat,
    "slope": _parse_slope,
    "stairs": _parse_stairs,
    "gap": _parse_gap,
    "rough": _parse_rough,
}


def _check_layout(patches: tuple[Patch, ...], extent: Region, source: str) -> None:
    """Patches must have unique names, lie inside the extent and not overlap one another."""
    for i, patch in enumerate(patches):
        where = f"{source}: patch '{patch.name}' (#{i})"
        region = patch.region
        if region.x_min < extent.x_min or region.x_max > extent.x_max:
            raise CourseConfigError(
                f"{where}: field 'x' [{region.x_min:g}, {region.x_max:g}] lies outside "
                f"the extent x [{extent.x_min:g}, {extent.x_max:g}]"
            )
        if region.y_min < extent.y_min or region.y_max > extent.y_max:
            raise CourseConfigError(
                f"{where}: field 'y' [{region.y_min:g}, {region.y_max:g}] lies outside "
                f"the extent y [{extent.y_min:g}, {extent.y_max:g}]"
            )
        for j, earlier in enumerate(patches[:i]):
            if earlier.name == patch.name:
                raise CourseConfigError(f"{where}: field 'name' repeats the name of patch #{j}")
            if earlier.region.overlaps(region):
                raise CourseConfigError(
                    f"{where}: fields 'x'/'y': region x [{region.x_min:g}, {region.x_max:g}] y "
                    f"[{region.y_min:g}, {region.y_max:g}] overlaps patch '{earlier.name}' (#{j})"
                )
