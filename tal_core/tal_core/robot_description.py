"""Robot description: a URDF plus a small robot YAML naming legs, joints, frames and limits.

The YAML (see ``config/robots/hyq.yaml``) maps the robot onto the tal conventions: legs in the order
LF, RF, LH, RH, joints per leg HAA, HFE, KFE ("canonical order", 12 joints). Limits default to the
URDF ``<limit>`` tags and may be overridden in the YAML, per joint kind (``HFE``) or per URDF joint name
(``lf_hfe_joint``, which wins over the kind). Torque limits may be a joint-angle-dependent table of
``[q_rad, tau_max_Nm]`` breakpoints, linearly interpolated (HyQ's HFE/KFE linkages make the real
limit angle dependent).

This module reads the URDF with the standard XML parser only; Pinocchio lives in ``robot_model``.
"""

from __future__ import annotations

import math
import os
import sys
import xml.etree.ElementTree as ElementTree
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tal_core.errors import InputError, RobotConfigError
from tal_core.legs import JOINT_KINDS, JOINTS_PER_LEG, LEG_NAMES, LEGS, NUM_LEGS, Leg, PerLeg
from tal_core.rotations import quat_xyzw_from_rotation

EXAMPLE_ROBOT_DATA_ENV = "TAL_EXAMPLE_ROBOT_DATA_DIR"
EXAMPLE_ROBOT_DATA_SCHEME = "example-robot-data://"
_EXAMPLE_ROBOT_DATA_SUBDIR = Path("cmeel.prefix") / "share" / "example-robot-data"
NUM_JOINTS = NUM_LEGS * JOINTS_PER_LEG

_REQUIRED_KEYS = (
    "name",
    "urdf",
    "base_frame",
    "joints",
    "foot_frames",
    "foot_radius_m",
    "nominal_joint_positions_rad",
)
_OPTIONAL_KEYS = ("hip_frames", "limits", "imu")
_LIMIT_KEYS = ("position_rad", "velocity_rad_s", "torque_Nm")
_IMU_KEYS = ("position_m", "orientation_xyzw", "link")
_ACTUATED_URDF_TYPES = ("revolute", "prismatic")


# --- Locating files ---
def find_example_robot_data_dir() -> Path:
    """Return the ``share/example-robot-data`` directory of the example-robot-data package.

    ``$TAL_EXAMPLE_ROBOT_DATA_DIR`` wins when set; otherwise every ``sys.path`` entry is searched for
    ``cmeel.prefix/share/example-robot-data`` (where the PyPI wheel installs it).
    """
    override = os.environ.get(EXAMPLE_ROBOT_DATA_ENV)
    if override:
        path = Path(override).expanduser()
        if not path.is_dir():
            raise RobotConfigError(f"{EXAMPLE_ROBOT_DATA_ENV}={override!r} is not a directory")
        return path
    for entry in sys.path:
        candidate = Path(entry or ".") / _EXAMPLE_ROBOT_DATA_SUBDIR
        if candidate.is_dir():
            return candidate
    raise RobotConfigError(
        f"example-robot-data not found: no sys.path entry contains {_EXAMPLE_ROBOT_DATA_SUBDIR}; "
        f"install it (pip install example-robot-data) or set {EXAMPLE_ROBOT_DATA_ENV}"
    )


def resolve_urdf_path(spec: str, yaml_dir: Path, source: Path | str = "<robot yaml>") -> Path:
    """Resolve the YAML ``urdf`` field: ``example-robot-data://<rel>``, an absolute path, or a path
    relative to the YAML's directory. Raises RobotConfigError if the file does not exist."""
    if spec.startswith(EXAMPLE_ROBOT_DATA_SCHEME):
        path = find_example_robot_data_dir() / spec[len(EXAMPLE_ROBOT_DATA_SCHEME) :]
    else:
        path = Path(spec).expanduser()
        if not path.is_absolute():
            path = yaml_dir / path
    if not path.is_file():
        raise RobotConfigError(f"{source}: field 'urdf': file {str(path)!r} (from {spec!r}) does not exist")
    return path.resolve()


def shipped_robot_names() -> tuple[str, ...]:
    """Names of the robot YAMLs shipped in ``tal_core/config/robots``."""
    robots_dir = files("tal_core") / "config" / "robots"
    return tuple(sorted(entry.name[:-5] for entry in robots_dir.iterdir() if entry.name.endswith(".yaml")))


# --- URDF summary (joints, links, limits) ---
@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint with its ``<limit>`` values (None where the URDF gives none). Units: rad or m,
    rad/s or m/s, N m or N, as the URDF spec defines them for the joint type."""

    name: str
    joint_type: str
    lower: float | None
    upper: float | None
    velocity: float | None
    effort: float | None
    parent: str = ""  # parent link
    child: str = ""  # child link
    origin_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)  # [m] child frame in the parent frame
    origin_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)  # [rad] fixed-axis roll, pitch, yaw


@dataclass(frozen=True)
class UrdfSummary:
    """Names of links and joints of a URDF and the joints' limits; enough to validate a robot YAML."""

    path: Path
    links: frozenset[str]
    joints: Mapping[str, UrdfJoint]

    @property
    def frame_names(self) -> frozenset[str]:
        """Names Pinocchio turns into frames: every link and every joint."""
        return self.links | frozenset(self.joints)


def read_urdf_summary(path: Path) -> UrdfSummary:
    """Parse the top-level ``<link>`` and ``<joint>`` elements of a URDF (transmissions are skipped)."""
    try:
        root = ElementTree.parse(path).getroot()
    except (ElementTree.ParseError, OSError) as error:
        raise RobotConfigError(f"{path}: cannot parse URDF: {error}") from None
    links = frozenset(link.get("name", "") for link in root.findall("link"))
    joints: dict[str, UrdfJoint] = {}
    for element in root.findall("joint"):
        limit = element.find("limit")
        values = {
            key: None if limit is None else _optional_float(limit.get(key))
            for key in ("lower", "upper", "velocity", "effort")
        }
        name = element.get("name", "")
        origin = element.find("origin")
        parent, child = element.find("parent"), element.find("child")
        try:
            xyz = _triple(None if origin is None else origin.get("xyz"))
            rpy = _triple(None if origin is None else origin.get("rpy"))
        except ValueError as error:
            raise RobotConfigError(f"{path}: joint {name!r}: bad <origin>: {error}") from None
        joints[name] = UrdfJoint(name, element.get("type", ""), **values,
                                 parent="" if parent is None else parent.get("link", ""),
                                 child="" if child is None else child.get("link", ""), origin_xyz=xyz, origin_rpy=rpy)
    return UrdfSummary(Path(path), links, joints)


def _triple(text: str | None) -> tuple[float, float, float]:
    if text is None:
        return (0.0, 0.0, 0.0)
    values = [float(item) for item in text.split()]
    if len(values) != 3:
        raise ValueError(f"expected 3 numbers, got {text!r}")
    return (values[0], values[1], values[2])


def _rotation_from_rpy(rpy: Sequence[float]) -> np.ndarray:
    """URDF rpy (fixed axes x, y, z): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    (cr, sr), (cp, sp), (cy, sy) = ((math.cos(a), math.sin(a)) for a in rpy)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _fixed_chain(urdf: UrdfSummary, frame: str) -> tuple[str, np.ndarray]:
    """(top link, top_T_frame 4x4): ``frame`` (a link, or a joint: its child link) walked up through fixed
    joints to the first link that hangs on a moving joint or is the root."""
    link = urdf.joints[frame].child if frame in urdf.joints else frame
    parent_joint = {joint.child: joint for joint in urdf.joints.values()}
    transform = np.eye(4)
    seen = set()
    while link in parent_joint and parent_joint[link].joint_type == "fixed" and link not in seen:
        seen.add(link)
        joint = parent_joint[link]
        step = np.eye(4)
        step[:3, :3] = _rotation_from_rpy(joint.origin_rpy)
        step[:3, 3] = joint.origin_xyz
        transform = step @ transform
        link = joint.parent
    return link, transform


def fixed_frame_pose(urdf: UrdfSummary, base_frame: str, frame: str) -> tuple[np.ndarray, np.ndarray]:
    """(position [m] (3,), rotation (3, 3)) of ``frame`` in ``base_frame``, both URDF links (or joints) rigidly
    attached to one another through fixed joints; RobotConfigError otherwise."""
    for name in (base_frame, frame):
        if name not in urdf.frame_names:
            raise RobotConfigError(f"{urdf.path}: {name!r} is neither a link nor a joint")
    base_top, top_T_base = _fixed_chain(urdf, base_frame)
    frame_top, top_T_frame = _fixed_chain(urdf, frame)
    if base_top != frame_top:
        raise RobotConfigError(f"{urdf.path}: {frame!r} is not rigidly attached to {base_frame!r} (fixed joints "
                               f"lead to {frame_top!r} and {base_top!r})")
    base_T_frame = np.linalg.inv(top_T_base) @ top_T_frame
    return base_T_frame[:3, 3].copy(), base_T_frame[:3, :3].copy()


def _optional_float(text: str | None) -> float | None:
    return None if text is None else float(text)


# --- Torque limit tables ---
@dataclass(frozen=True, eq=False)
class TorqueLimitTable:
    """Maximum joint torque [N m] as a piecewise-linear function of the joint angle [rad].

    Outside the breakpoints the end values hold. A constant limit is a single breakpoint. The
    minimum torque is the negative of the maximum (the actuators are symmetric).
    """

    joint_angles_rad: np.ndarray  # (n,) [rad] breakpoints, strictly increasing
    max_torques: np.ndarray  # (n,) [N m] maximum torque at each breakpoint, > 0

    @classmethod
    def constant(cls, max_torque_Nm: float) -> TorqueLimitTable:
        return cls(_frozen_array([0.0]), _frozen_array([max_torque_Nm]))

    def max_torque(self, joint_angle_rad: float) -> float:
        """Maximum torque [N m] at ``joint_angle_rad`` [rad]."""
        if self.max_torques.size == 1:  # constant limit: skip np.interp, this runs per joint per tick
            return float(self.max_torques[0])
        return float(np.interp(joint_angle_rad, self.joint_angles_rad, self.max_torques))


# --- The description ---
@dataclass(frozen=True, eq=False)
class RobotDescription:
    """Everything tal needs to know about a quadruped besides its URDF dynamics.

    Per-joint arrays have 12 entries in canonical order LF, RF, LH, RH x HAA, HFE, KFE; index them with
    ``joint_index(leg, kind)`` or ``leg_joint_slice(leg)``. Arrays are read-only.
    """

    name: str
    source: Path  # the robot YAML this came from
    urdf_path: Path  # absolute path of the URDF
    base_frame: str  # URDF link rigidly attached to the floating base (x fwd, z up)
    joint_names: tuple[str, ...]  # 12 URDF joint names, canonical order
    foot_frames: PerLeg[str]  # frame at the centre of each foot sphere
    hip_frames: PerLeg[str]  # frame at each leg's HAA joint
    foot_radius_m: float  # [m] radius of the foot sphere
    position_lower_rad: np.ndarray  # (12,) [rad] joint position lower limits
    position_upper_rad: np.ndarray  # (12,) [rad] joint position upper limits
    velocity_limit_rad_s: np.ndarray  # (12,) [rad/s] joint speed limits (symmetric)
    torque_limit_tables: tuple[TorqueLimitTable, ...]  # 12 tables, [N m] over [rad]
    nominal_joint_positions_rad: np.ndarray  # (12,) [rad] nominal standing pose
    imu_position_base_m: np.ndarray  # (3,) [m] IMU origin in the base frame
    base_quat_imu_xyzw: np.ndarray  # (4,) orientation of the IMU frame in the base frame (x, y, z, w)

    @staticmethod
    def joint_index(leg: Leg, kind: str) -> int:
        """Canonical index (0..11) of joint ``kind`` ('HAA', 'HFE', 'KFE') of ``leg``."""
        return int(leg) * JOINTS_PER_LEG + JOINT_KINDS.index(kind)

    @staticmethod
    def leg_joint_slice(leg: Leg) -> slice:
        """Slice of the leg's HAA, HFE, KFE entries in canonical per-joint arrays."""
        start = int(leg) * JOINTS_PER_LEG
        return slice(start, start + JOINTS_PER_LEG)

    def leg_joint_names(self, leg: Leg) -> tuple[str, ...]:
        """URDF names of the leg's HAA, HFE, KFE joints."""
        return self.joint_names[self.leg_joint_slice(leg)]

    def torque_limits(
        self, joint_positions_rad: Sequence[float] | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(tau_min, tau_max)`` [N m], each (12,), at the canonical joint positions [rad]."""
        q = np.asarray(joint_positions_rad, dtype=float)
        if q.shape != (NUM_JOINTS,):
            raise InputError(f"torque_limits expects {NUM_JOINTS} joint positions, got shape {q.shape}")
        if not np.isfinite(q).all():
            bad = np.flatnonzero(~np.isfinite(q)).tolist()
            raise InputError(f"torque_limits: non-finite joint position(s) at index {bad}")
        constant = self.__dict__.get("_constant_tau_max")
        if constant is None:
            constant = (np.array([table.max_torques[0] for table in self.torque_limit_tables])
                        if all(len(table.joint_angles_rad) == 1 for table in self.torque_limit_tables) else False)
            object.__setattr__(self, "_constant_tau_max", constant)  # frozen: a cache, not state
        if constant is not False:
            # Constant limits (no angle table): skip the per-joint interpolation, called at 1 kHz.
            tau_max = constant.copy()
        else:
            tau_max = np.array(
                [table.max_torque(angle) for table, angle in zip(self.torque_limit_tables, q, strict=True)]
            )
        return -tau_max, tau_max


def load_robot_description(path_or_name: str | Path = "hyq") -> RobotDescription:
    """Load a robot YAML by shipped name (``"hyq"``, ``"solo12"``) or by file path."""
    path = _locate_robot_yaml(path_or_name)
    document = _read_yaml_mapping(path)
    return _build_description(document, path)


def _locate_robot_yaml(path_or_name: str | Path) -> Path:
    text = str(path_or_name)
    looks_like_path = isinstance(path_or_name, Path) or os.sep in text or text.endswith((".yaml", ".yml"))
    if looks_like_path:
        path = Path(text).expanduser()
        if not path.is_file():
            raise RobotConfigError(f"robot YAML {text!r} does not exist")
        return path.resolve()
    shipped = files("tal_core") / "config" / "robots" / f"{text}.yaml"
    if not shipped.is_file():
        raise RobotConfigError(f"unknown robot {text!r}; shipped robots: {', '.join(shipped_robot_names())}")
    return Path(str(shipped))


def _read_yaml_mapping(path: Path) -> dict[str, Any]:
    try:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as error:
        raise RobotConfigError(f"{path}: cannot read robot YAML: {error}") from None
    if not isinstance(document, dict):
        raise RobotConfigError(f"{path}: robot YAML must be a mapping at the top level")
    return document


class _Fields:
    """Helpers that validate YAML values and name the file and field in every error."""

    def __init__(self, source: Path) -> None:
        self.source = source

    def error(self, field: str, message: str) -> RobotConfigError:
        return RobotConfigError(f"{self.source}: field '{field}': {message}")

    def check_keys(
        self, mapping: Any, field: str, required: Sequence[str], optional: Sequence[str] = ()
    ) -> None:
        if not isinstance(mapping, dict):
            raise self.error(field, f"expected a mapping, got {type(mapping).__name__}")
        unknown = sorted(set(mapping) - set(required) - set(optional))
        if unknown:
            raise self.error(field, f"unknown key(s) {unknown}; allowed: {sorted([*required, *optional])}")
        missing = [key for key in required if key not in mapping]
        if missing:
            raise self.error(field, f"missing key(s) {missing}")

    def string(self, value: Any, field: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.error(field, f"expected a non-empty string, got {value!r}")
        return value

    def number(self, value: Any, field: str, minimum: float = -math.inf) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(field, f"expected a finite number, got {value!r}")
        if value < minimum:
            raise self.error(field, f"must be >= {minimum}, got {value}")
        return float(value)

    def numbers(self, value: Any, field: str, count: int) -> list[float]:
        if not isinstance(value, (list, tuple)) or len(value) != count:
            raise self.error(field, f"expected a list of {count} numbers, got {value!r}")
        return [self.number(item, f"{field}[{i}]") for i, item in enumerate(value)]

    def per_leg(self, value: Any, field: str) -> dict[str, Any]:
        self.check_keys(value, field, LEG_NAMES)
        return value


def _build_description(document: dict[str, Any], source: Path) -> RobotDescription:
    fields = _Fields(source)
    fields.check_keys(document, "<top level>", _REQUIRED_KEYS, _OPTIONAL_KEYS)
    urdf_path = resolve_urdf_path(fields.string(document["urdf"], "urdf"), source.parent, source)
    urdf = read_urdf_summary(urdf_path)

    joint_names = _parse_joint_names(fields, document["joints"], urdf)
    base_frame = _parse_frame(fields, document["base_frame"], "base_frame", urdf)
    foot_frames = _parse_leg_frames(fields, document["foot_frames"], "foot_frames", urdf)
    haa_names = {leg.name: joint_names[RobotDescription.joint_index(leg, "HAA")] for leg in LEGS}
    hip_frames = _parse_leg_frames(fields, document.get("hip_frames", haa_names), "hip_frames", urdf)

    overrides = document.get("limits", {}) or {}
    fields.check_keys(overrides, "limits", (), _LIMIT_KEYS)
    lower, upper = _position_limits(fields, overrides.get("position_rad", {}), joint_names, urdf)
    velocity = _velocity_limits(fields, overrides.get("velocity_rad_s", {}), joint_names, urdf)
    torque_tables = _torque_tables(fields, overrides.get("torque_Nm", {}), joint_names, urdf)

    nominal = _parse_nominal(fields, document["nominal_joint_positions_rad"], joint_names, lower, upper)
    imu_position, imu_quat = _parse_imu(fields, document.get("imu", {}) or {}, urdf, base_frame)
    return RobotDescription(
        name=fields.string(document["name"], "name"),
        source=source,
        urdf_path=urdf_path,
        base_frame=base_frame,
        joint_names=joint_names,
        foot_frames=foot_frames,
        hip_frames=hip_frames,
        foot_radius_m=fields.number(document["foot_radius_m"], "foot_radius_m", minimum=0.0),
        position_lower_rad=_frozen_array(lower),
        position_upper_rad=_frozen_array(upper),
        velocity_limit_rad_s=_frozen_array(velocity),
        torque_limit_tables=torque_tables,
        nominal_joint_positions_rad=_frozen_array(nominal),
        imu_position_base_m=_frozen_array(imu_position),
        base_quat_imu_xyzw=_frozen_array(imu_quat),
    )


def _parse_joint_names(fields: _Fields, value: Any, urdf: UrdfSummary) -> tuple[str, ...]:
    per_leg = fields.per_leg(value, "joints")
    names: list[str] = []
    for leg_name in LEG_NAMES:
        leg_field = f"joints.{leg_name}"
        leg_joints = per_leg[leg_name]
        if not isinstance(leg_joints, list) or len(leg_joints) != JOINTS_PER_LEG:
            raise fields.error(
                leg_field,
                f"expected {JOINTS_PER_LEG} joint names ({', '.join(JOINT_KINDS)}), got {leg_joints!r}",
            )
        for kind, joint_name in zip(JOINT_KINDS, leg_joints, strict=True):
            field = f"{leg_field}.{kind}"
            joint_name = fields.string(joint_name, field)
            if joint_name not in urdf.joints:
                raise fields.error(field, f"joint {joint_name!r} not in URDF {urdf.path}")
            joint_type = urdf.joints[joint_name].joint_type
            if joint_type not in _ACTUATED_URDF_TYPES:
                raise fields.error(
                    field, f"joint {joint_name!r} is {joint_type!r}, not {_ACTUATED_URDF_TYPES}"
                )
            names.append(joint_name)
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise fields.error("joints", f"joint(s) {duplicates} listed more than once")
    return tuple(names)


def _parse_frame(fields: _Fields, value: Any, field: str, urdf: UrdfSummary) -> str:
    name = fields.string(value, field)
    if name not in urdf.frame_names:
        raise fields.error(field, f"frame {name!r} is neither a link nor a joint of URDF {urdf.path}")
    return name


def _parse_leg_frames(fields: _Fields, value: Any, field: str, urdf: UrdfSummary) -> PerLeg[str]:
    per_leg = fields.per_leg(value, field)
    return PerLeg.from_sequence(
        [_parse_frame(fields, per_leg[name], f"{field}.{name}", urdf) for name in LEG_NAMES]
    )


def _override_for(overrides: dict[str, Any], joint_name: str, joint_index: int) -> tuple[str, Any] | None:
    """The YAML override for a joint: by URDF joint name first, else by joint kind; None if absent."""
    if joint_name in overrides:
        return joint_name, overrides[joint_name]
    kind = JOINT_KINDS[joint_index % JOINTS_PER_LEG]
    if kind in overrides:
        return kind, overrides[kind]
    return None


def _check_override_keys(fields: _Fields, overrides: Any, field: str, joint_names: Sequence[str]) -> dict:
    fields.check_keys(overrides, field, (), [*JOINT_KINDS, *joint_names])
    return overrides


def _urdf_limit(fields: _Fields, urdf: UrdfSummary, joint_name: str, attribute: str, field: str) -> float:
    value = getattr(urdf.joints[joint_name], attribute)
    if value is None:
        raise fields.error(field, f"URDF gives no {attribute} limit for joint {joint_name!r}; set it here")
    return value


def _position_limits(
    fields: _Fields, overrides: Any, joint_names: Sequence[str], urdf: UrdfSummary
) -> tuple[list[float], list[float]]:
    field = "limits.position_rad"
    overrides = _check_override_keys(fields, overrides, field, joint_names)
    lower, upper = [], []
    for index, joint_name in enumerate(joint_names):
        override = _override_for(overrides, joint_name, index)
        if override is None:
            low = _urdf_limit(fields, urdf, joint_name, "lower", field)
            high = _urdf_limit(fields, urdf, joint_name, "upper", field)
            origin = f"URDF joint {joint_name!r}"
        else:
            key, value = override
            low, high = fields.numbers(value, f"{field}.{key}", 2)
            origin = f"{field}.{key}"
        if not low < high:
            raise fields.error(
                field, f"inverted position limits [{low}, {high}] for joint {joint_name!r} (from {origin})"
            )
        lower.append(low)
        upper.append(high)
    return lower, upper


def _velocity_limits(
    fields: _Fields, overrides: Any, joint_names: Sequence[str], urdf: UrdfSummary
) -> list[float]:
    field = "limits.velocity_rad_s"
    overrides = _check_override_keys(fields, overrides, field, joint_names)
    limits = []
    for index, joint_name in enumerate(joint_names):
        override = _override_for(overrides, joint_name, index)
        if override is None:
            limit = _urdf_limit(fields, urdf, joint_name, "velocity", field)
        else:
            limit = fields.number(override[1], f"{field}.{override[0]}")
        if not limit > 0.0:
            raise fields.error(field, f"velocity limit of joint {joint_name!r} must be > 0, got {limit}")
        limits.append(limit)
    return limits


def _torque_tables(
    fields: _Fields, overrides: Any, joint_names: Sequence[str], urdf: UrdfSummary
) -> tuple[TorqueLimitTable, ...]:
    field = "limits.torque_Nm"
    overrides = _check_override_keys(fields, overrides, field, joint_names)
    tables = []
    for index, joint_name in enumerate(joint_names):
        override = _override_for(overrides, joint_name, index)
        if override is None:
            limit = _urdf_limit(fields, urdf, joint_name, "effort", field)
            if not limit > 0.0:
                raise fields.error(
                    field, f"URDF effort limit of joint {joint_name!r} must be > 0, got {limit}"
                )
            tables.append(TorqueLimitTable.constant(limit))
        else:
            tables.append(_parse_torque_override(fields, override[1], f"{field}.{override[0]}"))
    return tuple(tables)


def _parse_torque_override(fields: _Fields, value: Any, field: str) -> TorqueLimitTable:
    """A number (constant limit) or a list of ``[q_rad, tau_max_Nm]`` breakpoints, q strictly increasing."""
    if not isinstance(value, list):
        limit = fields.number(value, field)
        if not limit > 0.0:
            raise fields.error(field, f"torque limit must be > 0, got {limit}")
        return TorqueLimitTable.constant(limit)
    if len(value) < 2:
        raise fields.error(field, "a torque table needs at least 2 [q_rad, tau_max_Nm] breakpoints")
    rows = np.array([fields.numbers(row, f"{field}[{i}]", 2) for i, row in enumerate(value)])
    if np.any(np.diff(rows[:, 0]) <= 0.0):
        raise fields.error(field, f"breakpoint angles must be strictly increasing, got {rows[:, 0].tolist()}")
    if np.any(rows[:, 1] <= 0.0):
        raise fields.error(field, f"maximum torques must be > 0, got {rows[:, 1].tolist()}")
    return TorqueLimitTable(_frozen_array(rows[:, 0]), _frozen_array(rows[:, 1]))


def _parse_nominal(
    fields: _Fields, value: Any, joint_names: Sequence[str], lower: Sequence[float], upper: Sequence[float]
) -> list[float]:
    per_leg = fields.per_leg(value, "nominal_joint_positions_rad")
    nominal: list[float] = []
    for leg_name in LEG_NAMES:
        nominal += fields.numbers(
            per_leg[leg_name], f"nominal_joint_positions_rad.{leg_name}", JOINTS_PER_LEG
        )
    for joint_name, angle, low, high in zip(joint_names, nominal, lower, upper, strict=True):
        if not low <= angle <= high:
            raise fields.error(
                "nominal_joint_positions_rad",
                f"{angle} rad for joint {joint_name!r} is outside its limits [{low}, {high}]",
            )
    return nominal


def _parse_imu(fields: _Fields, value: Any, urdf: UrdfSummary, base_frame: str) -> tuple[list[float], list[float]]:
    """The IMU's pose in the base frame: from the URDF's fixed joints when ``imu.link`` names its link, else
    ``position_m`` / ``orientation_xyzw`` (default: identity at the base origin)."""
    fields.check_keys(value, "imu", (), _IMU_KEYS)
    if "link" in value:
        if "position_m" in value or "orientation_xyzw" in value:
            raise fields.error("imu", "give either link (pose from the URDF) or position_m/orientation_xyzw")
        link = _parse_frame(fields, value["link"], "imu.link", urdf)
        try:
            position, rotation = fixed_frame_pose(urdf, base_frame, link)
        except RobotConfigError as error:
            raise fields.error("imu.link", str(error)) from None
        return position.tolist(), quat_xyzw_from_rotation(rotation).tolist()
    position = fields.numbers(value.get("position_m", [0.0, 0.0, 0.0]), "imu.position_m", 3)
    quat = np.array(
        fields.numbers(value.get("orientation_xyzw", [0.0, 0.0, 0.0, 1.0]), "imu.orientation_xyzw", 4)
    )
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > 1e-3:
        raise fields.error("imu.orientation_xyzw", f"quaternion must have unit norm, got norm {norm:.6f}")
    return position, (quat / norm).tolist()


def _frozen_array(values: Sequence[float] | np.ndarray) -> np.ndarray:
    array = np.array(values, dtype=float)
    array.setflags(write=False)
    return array
