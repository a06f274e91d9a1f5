"""Convert a robot log in CSV into a rosbag2 MCAP bag through a YAML column map.

One CSV row is one sample time. The map says which column is the time, which columns are which joint
signals, IMU axes and (optionally) the ground-truth pose and twist, with their units and extra scale
factors. Example (the shipped, documented one is ``tal_core/config/csv_maps/hyq_example.yaml``)::

    time: {column: t, unit: ms}
    joint_states:
      joints: [lf_haa_joint, lf_hfe_joint, ...]
      position: {column: "q_{joint}", unit: deg}        # {joint} is replaced by each joint name
      velocity: {column: "dq_{joint}", unit: deg/s}
      effort: {column: "tau_{joint}", unit: N m, scale: 1.0}
    imu:
      angular_velocity: {x: {column: gx, unit: deg/s}, y: ..., z: ...}
      linear_acceleration: {x: {column: ax, unit: g}, y: ..., z: ...}
    foot_contacts:                                       # robots with foot sensors (optional)
      legs: [FL, FR, RL, RR]                             # the log's names of LF, RF, LH, RH ({leg})
      force: {column: "foot_force_{leg}", unit: count}   # raw counts (calibrated by the estimator) or N
      in_contact: {column: "contact_{leg}", unit: "-"}   # binary flags: non-zero is contact

A per-joint or per-leg signal names its columns either with a pattern (``column`` with ``{joint}`` /
``{leg}``) or as a list (``columns``, one name per entry of ``joints``, or per leg in tal's order LF, RF,
LH, RH), for logs whose columns are numbered in the robot's own motor or foot order::

      position: {columns: [q_3, q_4, q_5, q_0, q_1, q_2, q_9, q_10, q_11, q_6, q_7, q_8], unit: rad}
      force: {columns: [foot_force_1, foot_force_0, foot_force_3, foot_force_2], unit: count}

Columns of the CSV that the map does not name are ignored; a mapped column the CSV lacks is an error.

Foot contacts go to ``/foot_contacts`` (tal_msgs/ContactState, frame "base"): each foot's scalar force
reading in ``force[leg].z`` (what the estimator's ``contact_source:=force_sensor`` reads: raw counts with its
``foot_force_scale`` / ``foot_force_offset`` calibration, or newtons) and the flags in ``in_contact`` (what
``contact_source:=contact_flags`` reads). A log without joint torques maps no ``effort``.

Every value ends in SI units (rad, rad/s, N m, m, m/s, m/s^2) in the frames the graph uses (IMU and twist
in the base frame, pose in the world frame). Bad input is named precisely: a missing column names the
column, the map entry and the CSV header line; a bad unit names the column and the map's line; a cell
that is not a number names the column and the CSV line. Rows whose time does not increase are skipped,
counted and logged (``ImportReport``). The CSV is streamed: memory does not grow with its length.

Usage: ``python -m tal_core.ros.csv_import LOG.csv --map MAP.yaml --out BAG [--skip-bad-rows]``.
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from geometry_msgs.msg import Point, Quaternion, Vector3
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState

from tal_core.errors import InputError
from tal_core.ros.bag_io import BagWriter
from tal_core.ros.node_utils import stamp_from_ns
from tal_msgs.msg import ContactState

LOG = logging.getLogger("tal.csv_import")

# unit -> (quantity, factor to SI)
UNITS: dict[str, tuple[str, float]] = {
    "s": ("time", 1.0), "ms": ("time", 1e-3), "us": ("time", 1e-6), "ns": ("time", 1e-9),
    "rad": ("angle", 1.0), "deg": ("angle", math.pi / 180.0),
    "rad/s": ("angular velocity", 1.0), "deg/s": ("angular velocity", math.pi / 180.0),
    "N m": ("torque", 1.0), "N mm": ("torque", 1e-3),
    "m": ("length", 1.0), "cm": ("length", 1e-2), "mm": ("length", 1e-3),
    "m/s": ("velocity", 1.0), "mm/s": ("velocity", 1e-3),
    "m/s^2": ("acceleration", 1.0), "g": ("acceleration", 9.80665),
    "N": ("force", 1.0), "count": ("force", 1.0),  # count: a raw sensor reading, calibrated downstream
    "-": ("dimensionless", 1.0),
}

# signal -> quantity its unit must measure
JOINT_SIGNALS = {"position": "angle", "velocity": "angular velocity", "effort": "torque"}
IMU_SIGNALS = {"angular_velocity": "angular velocity", "linear_acceleration": "acceleration"}
ODOM_SIGNALS = {"position": "length", "orientation_xyzw": "dimensionless", "linear_velocity": "velocity",
                "angular_velocity": "angular velocity"}
AXES = {"orientation_xyzw": ("x", "y", "z", "w")}
FOOT_SIGNALS = {"force": "force", "in_contact": "dimensionless"}
LEGS = ("LF", "RF", "LH", "RH")  # tal's leg order (ContactState)


class CsvImportError(InputError):
    """The CSV or its column map cannot be converted (the message names the column and the line)."""


@dataclass(frozen=True)
class Column:
    """One CSV column: its header name, SI factor (unit x scale) and where the map defines it."""

    name: str
    factor: float
    what: str  # e.g. "joint_states.position of lf_haa_joint"
    index: int = -1


@dataclass
class ImportReport:
    """What an import wrote and skipped."""

    rows: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    skipped_rows: dict[str, int] = field(default_factory=dict)

    def skip(self, reason: str) -> None:
        self.skipped_rows[reason] = self.skipped_rows.get(reason, 0) + 1


class _LineLoader(yaml.SafeLoader):
    """SafeLoader that remembers the line of every mapping (for error messages)."""


def _mapping_with_line(loader: _LineLoader, node: yaml.MappingNode) -> dict:
    mapping = loader.construct_mapping(node, deep=True)
    mapping["__line__"] = node.start_mark.line + 1
    return mapping


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_with_line)


@dataclass
class ColumnMap:
    """The parsed map: time column, joint names and per-signal columns, IMU and odometry axes, topics."""

    source: str
    time: Column
    time_offset_s: float
    joints: list[str]
    joint_columns: dict[str, list[Column]]  # signal -> one column per joint
    imu: dict[str, list[Column]]  # signal -> x, y, z
    odom: dict[str, list[Column]]  # signal -> axes
    topics: dict[str, str]
    feet: dict[str, list[Column]] = field(default_factory=dict)  # signal -> LF, RF, LH, RH

    @classmethod
    def load(cls, path: str | Path) -> ColumnMap:
        path = Path(path)
        try:
            raw = yaml.load(path.read_text(), Loader=_LineLoader)  # noqa: S506 (SafeLoader subclass)
        except (OSError, yaml.YAMLError) as exc:
            raise CsvImportError(f"column map {path}: cannot read it: {exc}") from None
        if not isinstance(raw, dict):
            raise CsvImportError(f"column map {path}: expected a mapping at the top level")
        return cls.from_dict(raw, str(path))

    @classmethod
    def from_dict(cls, raw: dict, source: str = "<map>") -> ColumnMap:
        def need(mapping: dict, key: str, where: str):
            if not isinstance(mapping, dict) or key not in mapping:
                line = mapping.get("__line__", "?") if isinstance(mapping, dict) else "?"
                raise CsvImportError(f"column map {source} line {line}: {where} needs '{key}'")
            return mapping[key]

        def column(spec: dict, quantity: str, what: str, name: str | None = None) -> Column:
            if not isinstance(spec, dict):
                raise CsvImportError(f"column map {source}: {what} must be a mapping with 'column' and 'unit'")
            line = spec.get("__line__", "?")
            if name is None:
                name = str(need(spec, "column", what))
            unit = str(spec.get("unit", ""))
            known = UNITS.get(unit)
            if known is None or known[0] != quantity:
                choices = ", ".join(u for u, (q, _) in UNITS.items() if q == quantity)
                raise CsvImportError(f"column map {source} line {line}: column '{name}' ({what}) has unit "
                                     f"{unit!r}, which is not a unit of {quantity} ({choices})")
            scale = spec.get("scale", 1.0)
            if not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale == 0.0:
                raise CsvImportError(f"column map {source} line {line}: column '{name}' ({what}) has scale "
                                     f"{scale!r}; it must be a finite non-zero number")
            return Column(name, known[1] * float(scale), what)

        def per_item(spec: dict, quantity: str, what: str, items: list[str] | tuple[str, ...],
                     labels: list[str] | tuple[str, ...], placeholder: str) -> list[Column]:
            """One column per item: ``columns`` (a list in items order) or ``column`` with {placeholder}."""
            if isinstance(spec, dict) and "columns" in spec:
                listed = spec["columns"]
                line = spec.get("__line__", "?")
                if "column" in spec:
                    raise CsvImportError(f"column map {source} line {line}: {what} gives both 'column' and "
                                         f"'columns'; give one")
                names = [str(n) for n in listed] if isinstance(listed, list) else []
                if len(names) != len(items) or len(set(names)) != len(names):
                    raise CsvImportError(f"column map {source} line {line}: {what}.columns must list {len(items)} "
                                         f"distinct column names (one per {placeholder}: {', '.join(labels)}), "
                                         f"got {listed!r}")
                return [column(spec, quantity, f"{what} of {label}", name=n) for n, label in zip(names, labels)]
            if not isinstance(spec, dict):
                column(spec, quantity, what)  # raises: not a mapping
            pattern = str(need(spec, "column", what))
            return [column(spec, quantity, f"{what} of {label}", name=pattern.replace("{" + placeholder + "}", item))
                    for item, label in zip(items, labels, strict=True)]

        time_spec = need(raw, "time", "the map")
        time_col = column(time_spec, "time", "time")
        offset = float(time_spec.get("offset_s", 0.0))
        topics = {"joint_states": "/joint_states", "imu": "/imu", "ground_truth": "/ground_truth/odom",
                  "foot_contacts": "/foot_contacts"}
        joints: list[str] = []
        joint_columns: dict[str, list[Column]] = {}
        js = raw.get("joint_states")
        if js is not None:
            joints = [str(j) for j in need(js, "joints", "joint_states")]
            if not joints or len(set(joints)) != len(joints):
                raise CsvImportError(f"column map {source}: joint_states.joints must be unique names, got {joints}")
            topics["joint_states"] = str(js.get("topic", topics["joint_states"]))
            for signal, quantity in JOINT_SIGNALS.items():
                if signal in js:
                    joint_columns[signal] = per_item(js[signal], quantity, f"joint_states.{signal}", joints,
                                                     joints, "joint")
        imu = cls._vectors(raw.get("imu"), IMU_SIGNALS, "imu", column, topics, "imu")
        odom = cls._vectors(raw.get("ground_truth"), ODOM_SIGNALS, "ground_truth", column, topics, "ground_truth")
        feet: dict[str, list[Column]] = {}
        fc = raw.get("foot_contacts")
        if fc is not None:
            names = [str(n) for n in fc.get("legs", LEGS)] if isinstance(fc, dict) else []
            if len(names) != len(LEGS) or len(set(names)) != len(names):
                raise CsvImportError(f"column map {source}: foot_contacts.legs must be four distinct names (the "
                                     f"log's LF, RF, LH, RH), got {names}")
            topics["foot_contacts"] = str(fc.get("topic", topics["foot_contacts"]))
            for signal, quantity in FOOT_SIGNALS.items():
                if signal in fc:
                    feet[signal] = per_item(fc[signal], quantity, f"foot_contacts.{signal}", names, LEGS, "leg")
            if not feet:
                raise CsvImportError(f"column map {source}: foot_contacts maps neither force nor in_contact")
        if not joint_columns and not imu and not odom and not feet:
            raise CsvImportError(f"column map {source}: maps no signal (joint_states, imu, ground_truth or "
                                 f"foot_contacts)")
        if odom and not {"position", "orientation_xyzw"} <= set(odom):
            raise CsvImportError(f"column map {source}: ground_truth needs at least position and orientation_xyzw")
        return cls(source, time_col, offset, joints, joint_columns, imu, odom, topics, feet)

    @staticmethod
    def _vectors(spec, signals: dict[str, str], section: str, column, topics: dict[str, str],
                 topic_key: str) -> dict[str, list[Column]]:
        if spec is None:
            return {}
        topics[topic_key] = str(spec.get("topic", topics[topic_key]))
        out = {}
        for signal, quantity in signals.items():
            if signal in spec:
                axes = AXES.get(signal, ("x", "y", "z"))
                entry = spec[signal]
                missing = [a for a in axes if not isinstance(entry, dict) or a not in entry]
                if missing:
                    raise CsvImportError(f"{section}.{signal} needs the axes {list(axes)}; missing {missing}")
                out[signal] = [column(entry[a], quantity, f"{section}.{signal}.{a}") for a in axes]
        return out

    def columns(self) -> Iterator[Column]:
        yield self.time
        for group in (*self.joint_columns.values(), *self.imu.values(), *self.odom.values(), *self.feet.values()):
            yield from group

    def bind(self, header: list[str], csv_name: str) -> None:
        """Resolve every column to its index in ``header``; CsvImportError names the first missing one."""
        index = {name.strip(): i for i, name in enumerate(header)}

        def resolve(c: Column) -> Column:
            if c.name not in index:
                raise CsvImportError(f"{csv_name} line 1: column '{c.name}' ({c.what}, map {self.source}) is not "
                                     f"in the header ({len(header)} columns)")
            return Column(c.name, c.factor, c.what, index[c.name])

        self.time = resolve(self.time)
        for group in (self.joint_columns, self.imu, self.odom, self.feet):
            for key, cols in group.items():
                group[key] = [resolve(c) for c in cols]


def _value(row: list[str], c: Column, csv_name: str, line: int) -> float:
    try:
        value = float(row[c.index])
    except (ValueError, IndexError):
        cell = row[c.index] if c.index < len(row) else "<missing cell>"
        raise CsvImportError(f"{csv_name} line {line}: column '{c.name}' ({c.what}) is {cell!r}, not a "
                             f"number") from None
    if not math.isfinite(value):
        raise CsvImportError(f"{csv_name} line {line}: column '{c.name}' ({c.what}) is {value}")
    return value * c.factor


def _messages(cmap: ColumnMap, row: list[str], csv_name: str, line: int, t_ns: int) -> list[tuple[str, object]]:
    stamp = stamp_from_ns(t_ns)
    out: list[tuple[str, object]] = []
    if cmap.joint_columns:
        msg = JointState(name=list(cmap.joints))
        msg.header.stamp, msg.header.frame_id = stamp, "base"
        for signal, cols in cmap.joint_columns.items():
            setattr(msg, signal, [_value(row, c, csv_name, line) for c in cols])
        out.append((cmap.topics["joint_states"], msg))
    if cmap.imu:
        msg = Imu()
        msg.header.stamp, msg.header.frame_id = stamp, "base"
        msg.orientation_covariance[0] = -1.0
        for signal, cols in cmap.imu.items():
            x, y, z = (_value(row, c, csv_name, line) for c in cols)
            setattr(msg, signal, Vector3(x=x, y=y, z=z))
        if "angular_velocity" not in cmap.imu:
            msg.angular_velocity_covariance[0] = -1.0
        if "linear_acceleration" not in cmap.imu:
            msg.linear_acceleration_covariance[0] = -1.0
        out.append((cmap.topics["imu"], msg))
    if cmap.odom:
        msg = Odometry()
        msg.header.stamp, msg.header.frame_id, msg.child_frame_id = stamp, "world", "base"
        values = {signal: [_value(row, c, csv_name, line) for c in cols] for signal, cols in cmap.odom.items()}
        msg.pose.pose.position = Point(x=values["position"][0], y=values["position"][1], z=values["position"][2])
        qx, qy, qz, qw = values["orientation_xyzw"]
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if not 0.9 < norm < 1.1:
            raise CsvImportError(f"{csv_name} line {line}: ground_truth.orientation_xyzw has norm {norm:.3f}, not a "
                                 f"unit quaternion")
        msg.pose.pose.orientation = Quaternion(x=qx / norm, y=qy / norm, z=qz / norm, w=qw / norm)
        for signal, target in (("linear_velocity", "linear"), ("angular_velocity", "angular")):
            if signal in values:
                x, y, z = values[signal]
                setattr(msg.twist.twist, target, Vector3(x=x, y=y, z=z))
        out.append((cmap.topics["ground_truth"], msg))
    if cmap.feet:
        msg = ContactState()
        msg.header.stamp, msg.header.frame_id = stamp, "base"
        if "force" in cmap.feet:
            msg.force = [Vector3(x=0.0, y=0.0, z=_value(row, c, csv_name, line)) for c in cmap.feet["force"]]
        if "in_contact" in cmap.feet:
            flags = [_value(row, c, csv_name, line) != 0.0 for c in cmap.feet["in_contact"]]
            msg.in_contact = flags
            msg.probability = [float(f) for f in flags]
        msg.penetration = [math.nan] * len(LEGS)
        msg.penetration_rate = [math.nan] * len(LEGS)
        out.append((cmap.topics["foot_contacts"], msg))
    return out


def import_csv(csv_path: str | Path, map_path: str | Path | ColumnMap, out: str | Path, *,
               skip_bad_rows: bool = False) -> ImportReport:
    """Convert ``csv_path`` into the bag folder ``out`` (must not exist or be empty).

    skip_bad_rows: a row with a non-numeric cell is skipped and counted instead of stopping the import
    (the bag written so far is kept and closed either way). Rows whose time does not increase are always
    skipped and counted."""
    cmap = map_path if isinstance(map_path, ColumnMap) else ColumnMap.load(map_path)
    csv_path = Path(csv_path)
    name = csv_path.name
    report = ImportReport()
    try:
        stream = csv_path.open(newline="")
    except OSError as exc:
        raise CsvImportError(f"cannot open {csv_path}: {exc}") from None
    with stream, BagWriter(out) as bag:
        rows = csv.reader(stream)
        header = next(rows, None)
        if header is None:
            raise CsvImportError(f"{name} line 1: the file is empty (no header)")
        cmap.bind(header, name)
        last_ns: int | None = None
        warned = False
        for line, row in enumerate(rows, start=2):
            if not row or all(not cell.strip() for cell in row):
                continue
            try:
                t_ns = round((_value(row, cmap.time, name, line) + cmap.time_offset_s) * 1e9)
                if last_ns is not None and t_ns <= last_ns:
                    report.skip("time not increasing")
                    if not warned:
                        LOG.warning("%s line %d: time %.6f s does not increase (previous %.6f s); row skipped "
                                    "(further ones counted only)", name, line, t_ns * 1e-9, last_ns * 1e-9)
                        warned = True
                    continue
                messages = _messages(cmap, row, name, line, t_ns)
            except CsvImportError:
                if not skip_bad_rows:
                    raise
                report.skip("bad cell")
                LOG.warning("%s", sys.exc_info()[1])
                continue
            for topic, msg in messages:
                bag.write(topic, msg, t_ns)
                report.messages[topic] = report.messages.get(topic, 0) + 1
            last_ns = t_ns
            report.rows += 1
    return report


def export_csv(bag: str | Path, cmap: ColumnMap, csv_path: str | Path) -> int:
    """The inverse of :func:`import_csv`: write the bag's mapped topics as CSV rows in the map's columns
    and units (one row per time at which every mapped topic has a message). Returns the row count.
    Rows are complete only: a stamp missing one of the topics is left out."""
    from tal_core.ros.bag_io import BagReader

    topics = []
    if cmap.joint_columns:
        topics.append(cmap.topics["joint_states"])
    if cmap.imu:
        topics.append(cmap.topics["imu"])
    if cmap.odom:
        topics.append(cmap.topics["ground_truth"])
    if cmap.feet:
        topics.append(cmap.topics["foot_contacts"])
    header = [c.name for c in cmap.columns()]
    pending: dict[int, dict[str, object]] = {}
    written = 0
    with Path(csv_path).open("w", newline="") as stream:
        out = csv.writer(stream)
        out.writerow(header)
        for message in BagReader(bag).messages(topics):
            slot = pending.setdefault(message.log_time_ns, {})
            slot[message.topic] = message.message
            if len(slot) < len(topics):
                continue
            del pending[message.log_time_ns]
            out.writerow([repr(v) for v in _row_values(cmap, message.log_time_ns, slot)])
            written += 1
            for stale in [t for t in pending if t < message.log_time_ns - 10**9]:  # bound memory
                del pending[stale]
    return written


def _row_values(cmap: ColumnMap, t_ns: int, slot: dict[str, object]) -> list[float]:
    values = [(t_ns * 1e-9 - cmap.time_offset_s) / cmap.time.factor]
    if cmap.joint_columns:
        js = slot[cmap.topics["joint_states"]]
        order = {name: i for i, name in enumerate(js.name)}
        for signal, cols in cmap.joint_columns.items():
            data = getattr(js, signal)
            values += [data[order[j]] / c.factor for j, c in zip(cmap.joints, cols, strict=True)]
    if cmap.imu:
        imu = slot[cmap.topics["imu"]]
        for signal, cols in cmap.imu.items():
            v = getattr(imu, signal)
            values += [getattr(v, a) / c.factor for a, c in zip("xyz", cols, strict=True)]
    if cmap.odom:
        odom = slot[cmap.topics["ground_truth"]]
        sources = {"position": (odom.pose.pose.position, "xyz"), "orientation_xyzw": (odom.pose.pose.orientation,
                   "xyzw"), "linear_velocity": (odom.twist.twist.linear, "xyz"),
                   "angular_velocity": (odom.twist.twist.angular, "xyz")}
        for signal, cols in cmap.odom.items():
            v, axes = sources[signal]
            values += [getattr(v, a) / c.factor for a, c in zip(axes, cols, strict=True)]
    if cmap.feet:
        feet = slot[cmap.topics["foot_contacts"]]
        if "force" in cmap.feet:
            values += [f.z / c.factor for f, c in zip(feet.force, cmap.feet["force"], strict=True)]
        if "in_contact" in cmap.feet:
            values += [float(flag) for flag in feet.in_contact]
    return values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Convert a robot log in CSV into a rosbag2 MCAP bag.")
    parser.add_argument("csv", type=Path, help="the CSV log (a header row, one row per sample time)")
    parser.add_argument("--map", type=Path, required=True, help="YAML column map (see tal_core/config/csv_maps)")
    parser.add_argument("--out", type=Path, required=True, help="bag folder to create")
    parser.add_argument("--skip-bad-rows", action="store_true", help="skip and count rows with a bad cell")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        report = import_csv(args.csv, args.map, args.out, skip_bad_rows=args.skip_bad_rows)
    except InputError as exc:
        LOG.error("%s", exc)
        return 2
    print(f"{args.out}: {report.rows} rows, messages {report.messages}, skipped {report.skipped_rows or 'none'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
