"""The simulation model under test: a sim_bridge configuration (robot, course, model effects) seen as a
flat vector of named physical parameters, with the default ground of the course as parameters too.

Parameter names carry their units. The nominal model is what the simulator really is: foot contact
compliance is the course's Kelvin-Voigt ground, shin/ground collisions are filtered, URDF joint damping is
zero and torques are clipped at the robot's limits (tal_sim_bridge.physics); so a fitted parameter is a
difference between the data and that simulator, not the simulator itself.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from tal_core.course_io import parse_course
from tal_core.terrain import Course, load_course
from tal_sim_bridge.effects import ModelEffects

from .errors import ModelConfigError

_VECTOR_EFFECTS = {
    "payload_offset_m": ("payload_offset_{}_m",),
    "imu_gyro_bias_rad_s": ("imu_gyro_bias_{}_rad_s",),
    "imu_accel_bias_m_s2": ("imu_accel_bias_{}_m_s2",),
}
GROUND_PARAMETERS = ("ground_stiffness_n_per_m", "ground_damping_ns_per_m", "foot_friction")


def _flat_effect_names() -> list[str]:
    names = []
    for f in dataclasses.fields(ModelEffects):
        if f.name in _VECTOR_EFFECTS:
            names.extend(_VECTOR_EFFECTS[f.name][0].format(axis) for axis in "xyz")
        else:
            names.append(f.name)
    return names


PARAMETER_NAMES: tuple[str, ...] = (*GROUND_PARAMETERS, *_flat_effect_names())


@dataclass(frozen=True)
class SimModel:
    """Robot name, course (its default ground carries the ground parameters) and model effects."""

    course: Course
    effects: ModelEffects = field(default_factory=ModelEffects)
    robot: str = "hyq"

    # -- flat parameter view ------------------------------------------------------------------------
    def values(self) -> dict[str, float]:
        """Every parameter by name [SI units in the name]."""
        out = {
            "ground_stiffness_n_per_m": float(self.course.default.stiffness_n_per_m),
            "ground_damping_ns_per_m": float(self.course.default.damping_ns_per_m),
            "foot_friction": float(self.course.default.friction),
        }
        for f in dataclasses.fields(ModelEffects):
            value = getattr(self.effects, f.name)
            if f.name in _VECTOR_EFFECTS:
                for axis, v in zip("xyz", value):
                    out[_VECTOR_EFFECTS[f.name][0].format(axis)] = float(v)
            else:
                out[f.name] = float(value)
        return out

    def with_values(self, values: dict[str, float]) -> SimModel:
        """A copy with some parameters replaced; unknown names are an error."""
        unknown = sorted(set(values) - set(PARAMETER_NAMES))
        if unknown:
            raise ModelConfigError(f"unknown model parameter(s) {unknown}; known: {list(PARAMETER_NAMES)}")
        merged = {**self.values(), **{k: float(v) for k, v in values.items()}}
        default = dataclasses.replace(
            self.course.default,
            stiffness_n_per_m=merged["ground_stiffness_n_per_m"],
            damping_ns_per_m=merged["ground_damping_ns_per_m"],
            friction=merged["foot_friction"],
            terrain=None,
        )
        kwargs: dict[str, object] = {}
        for f in dataclasses.fields(ModelEffects):
            if f.name in _VECTOR_EFFECTS:
                kwargs[f.name] = tuple(merged[_VECTOR_EFFECTS[f.name][0].format(a)] for a in "xyz")
            else:
                kwargs[f.name] = merged[f.name]
        try:
            effects = ModelEffects(**kwargs)  # type: ignore[arg-type]
        except ValueError as exc:
            raise ModelConfigError(str(exc)) from exc
        for name in GROUND_PARAMETERS:
            if not merged[name] > 0.0:
                raise ModelConfigError(f"{name} must be > 0, got {merged[name]}")
        return SimModel(dataclasses.replace(self.course, default=default), effects, self.robot)

    def differences(self, other: SimModel, rtol: float = 1e-9) -> dict[str, tuple[float, float]]:
        """Parameters that differ from ``other``: name -> (other's value, this value)."""
        mine, theirs = self.values(), other.values()
        return {
            k: (theirs[k], mine[k])
            for k in PARAMETER_NAMES
            if abs(mine[k] - theirs[k]) > rtol * max(1.0, abs(theirs[k]))
        }

    # -- files --------------------------------------------------------------------------------------
    @classmethod
    def from_yaml(cls, path: str | Path) -> SimModel:
        """Read a sim_bridge parameter YAML (``sim_bridge: ros__parameters: {robot, course, effects}``);
        a relative course path is relative to the YAML's folder (written files name the course file beside them;
        for the sim_bridge node pass its path with -p course:=...)."""
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
            params = data["sim_bridge"]["ros__parameters"]
        except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
            raise ModelConfigError(f"{path}: not a sim_bridge parameter file ({exc})") from exc
        course_ref = str(params.get("course", "flat_rigid"))
        candidate = path.parent / course_ref
        course = load_course(candidate if candidate.suffix in (".yaml", ".yml") and candidate.exists() else course_ref)
        try:
            effects = ModelEffects.from_mapping(dict(params.get("effects", {}) or {}))
        except ValueError as exc:
            raise ModelConfigError(f"{path}: {exc}") from exc
        return cls(course, effects, str(params.get("robot", "hyq")))

    @classmethod
    def nominal(cls, course: str | Course = "flat_rigid", robot: str = "hyq") -> SimModel:
        return cls(course if isinstance(course, Course) else load_course(course), ModelEffects(), robot)

    def write_yaml(self, path: str | Path) -> Path:
        """Write the model as a sim_bridge parameter YAML plus ``<stem>_course.yaml`` beside it (the
        course with this model's default ground). Returns the parameter file's path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        course_path = path.with_name(path.stem + "_course.yaml")
        course_path.write_text(yaml.safe_dump({"course": self._course_dict()}, sort_keys=False))
        parse_course(yaml.safe_load(course_path.read_text()), str(course_path))  # it must load back
        effects = {}
        for f in dataclasses.fields(ModelEffects):
            value = getattr(self.effects, f.name)
            effects[f.name] = [float(v) for v in value] if isinstance(value, tuple) else float(value)
        params = {"robot": self.robot, "course": course_path.name, "effects": effects}
        header = (
            "# Model configuration written by tal_sim2real (sim_bridge parameters; the course file beside it\n"
            "# carries the fitted ground). Use: sim_bridge --ros-args --params-file <this file>\n"
        )
        path.write_text(header + yaml.safe_dump({"sim_bridge": {"ros__parameters": params}}, sort_keys=False))
        return path

    def _course_dict(self) -> dict:
        source = Path(self.course.source)
        if source.exists():
            data = yaml.safe_load(source.read_text())["course"]
        else:
            data = yaml.safe_load(Path(load_course(self.course.name).source).read_text())["course"]
        d = self.course.default
        data["default"] = {
            "stiffness_n_per_m": float(d.stiffness_n_per_m),
            "damping_ns_per_m": float(d.damping_ns_per_m),
            "friction": float(d.friction),
            "height_m": float(d.height_m),
        }
        data["name"] = self.course.name
        return data
