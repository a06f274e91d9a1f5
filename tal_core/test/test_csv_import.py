"""CSV import through a YAML column map: round trip, the shipped example, and bad input named precisely."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import Quaternion, Vector3
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState

from tal_core.ros.bag_io import BagReader, BagWriter
from tal_core.ros.csv_import import ColumnMap, CsvImportError, export_csv, import_csv
from tal_core.ros.node_utils import stamp_from_ns

MAPS = Path(__file__).resolve().parents[1] / "tal_core" / "config" / "csv_maps"
EXAMPLE_MAP = MAPS / "hyq_example.yaml"
EXAMPLE_CSV = MAPS / "hyq_example.csv"
JOINTS = yaml.safe_load(EXAMPLE_MAP.read_text())["joint_states"]["joints"]


def random_bag(path: Path, n: int = 300, seed: int = 0) -> None:
    """n samples at 1 kHz of joint states, IMU and ground truth with random values."""
    rng = np.random.default_rng(seed)
    with BagWriter(path) as bag:
        for k in range(n):
            t_ns = 5 * 10**9 + k * 10**6
            stamp = stamp_from_ns(t_ns)
            js = JointState(name=list(JOINTS), position=rng.normal(size=12).tolist(),
                            velocity=rng.normal(size=12).tolist(), effort=(50 * rng.normal(size=12)).tolist())
            js.header.stamp = stamp
            imu = Imu(angular_velocity=Vector3(**dict(zip("xyz", rng.normal(size=3)))),
                      linear_acceleration=Vector3(**dict(zip("xyz", rng.normal(size=3) + [0, 0, 9.81]))))
            imu.header.stamp = stamp
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            odom = Odometry()
            odom.header.stamp = stamp
            odom.pose.pose.position.x, odom.pose.pose.position.y, odom.pose.pose.position.z = rng.normal(size=3)
            odom.pose.pose.orientation = Quaternion(**dict(zip("xyzw", q)))
            odom.twist.twist.linear = Vector3(**dict(zip("xyz", rng.normal(size=3))))
            odom.twist.twist.angular = Vector3(**dict(zip("xyz", rng.normal(size=3))))
            for topic, msg in (("/joint_states", js), ("/imu", imu), ("/ground_truth/odom", odom)):
                bag.write(topic, msg, t_ns)


def flat(msg) -> np.ndarray:
    if isinstance(msg, JointState):
        return np.r_[msg.position, msg.velocity, msg.effort]
    if isinstance(msg, Imu):
        a, f = msg.angular_velocity, msg.linear_acceleration
        return np.array([a.x, a.y, a.z, f.x, f.y, f.z])
    p, o, v, w = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear, msg.twist.twist.angular
    return np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w, v.x, v.y, v.z, w.x, w.y, w.z])


def test_a_bag_exported_in_robot_log_units_imports_back_to_the_same_messages(tmp_path: Path) -> None:
    random_bag(tmp_path / "original")
    cmap = ColumnMap.load(EXAMPLE_MAP)
    assert export_csv(tmp_path / "original", cmap, tmp_path / "log.csv") == 300
    with (tmp_path / "log.csv").open() as stream:  # the CSV really is in degrees, millimetres and g
        header = next(csv.reader(stream))
    assert header[0] == "t_ms" and "q_lf_haa_joint" in header and "acc_z" in header
    report = import_csv(tmp_path / "log.csv", EXAMPLE_MAP, tmp_path / "imported")
    assert report.rows == 300 and report.skipped_rows == {}
    assert report.messages == {"/joint_states": 300, "/imu": 300, "/ground_truth/odom": 300}
    original = list(BagReader(tmp_path / "original").messages())
    imported = list(BagReader(tmp_path / "imported").messages())
    assert [(m.topic, m.log_time_ns) for m in imported] == [(m.topic, m.log_time_ns) for m in original]
    for a, b in zip(original, imported, strict=True):
        np.testing.assert_allclose(flat(b.message), flat(a.message), rtol=1e-12, atol=1e-12)
    assert imported[0].message.header.stamp == original[0].message.header.stamp


def test_the_shipped_example_imports_with_its_map(tmp_path: Path) -> None:
    report = import_csv(EXAMPLE_CSV, EXAMPLE_MAP, tmp_path / "bag")
    assert report.rows == 20 and report.skipped_rows == {}
    first = next(BagReader(tmp_path / "bag").messages(["/imu"])).message
    assert 9.0 < first.linear_acceleration.z < 10.6  # g converted to m/s^2 while standing/trotting
    joints = next(BagReader(tmp_path / "bag").messages(["/joint_states"])).message
    assert list(joints.name) == JOINTS and max(abs(v) for v in joints.position) < 3.2  # radians


def write_csv(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    with path.open("w", newline="") as stream:
        out = csv.writer(stream)
        out.writerow(header)
        out.writerows(rows)
    return path


IMU_MAP = {"time": {"column": "t", "unit": "s"},
           "imu": {"angular_velocity": {a: {"column": f"g{a}", "unit": "rad/s"} for a in "xyz"},
                   "linear_acceleration": {a: {"column": f"a{a}", "unit": "m/s^2"} for a in "xyz"}}}
IMU_HEADER = ["t", "gx", "gy", "gz", "ax", "ay", "az"]


def test_a_missing_column_is_named_with_its_map_entry_and_the_header_line(tmp_path: Path) -> None:
    text = EXAMPLE_CSV.read_text().splitlines()
    header = text[0].split(",")
    drop = header.index("dq_rh_kfe_joint")
    cut = "\n".join(",".join(c for i, c in enumerate(line.split(",")) if i != drop) for line in text) + "\n"
    (tmp_path / "cut.csv").write_text(cut)
    with pytest.raises(CsvImportError, match=r"cut.csv line 1: column 'dq_rh_kfe_joint' "
                                             r"\(joint_states.velocity of rh_kfe_joint, map .*hyq_example.yaml\)"):
        import_csv(tmp_path / "cut.csv", EXAMPLE_MAP, tmp_path / "bag")


def test_a_bad_unit_names_the_column_and_the_map_line(tmp_path: Path) -> None:
    text = EXAMPLE_MAP.read_text().replace("unit: deg/s}", "unit: furlong/fortnight}", 1)
    (tmp_path / "map.yaml").write_text(text)
    line = next(i for i, s in enumerate(text.splitlines(), 1) if "furlong" in s)
    with pytest.raises(CsvImportError, match=rf"map.yaml line {line}: column 'dq_lf_haa_joint' \(joint_states."
                                             r"velocity of lf_haa_joint\) has unit 'furlong/fortnight', which is "
                                             r"not a unit of angular velocity \(rad/s, deg/s\)"):
        ColumnMap.load(tmp_path / "map.yaml")
    text = EXAMPLE_MAP.read_text().replace("{column: t_ms, unit: ms", "{column: t_ms, unit: deg", 1)
    (tmp_path / "map.yaml").write_text(text)
    with pytest.raises(CsvImportError, match=r"line 14: column 't_ms' \(time\) has unit 'deg'.*not a unit of time"):
        ColumnMap.load(tmp_path / "map.yaml")


def test_a_cell_that_is_not_a_number_names_the_column_and_the_line(tmp_path: Path) -> None:
    rows = [[0.001 * k, 0, 0, 0.1 * k, 0, 0, 9.81] for k in range(10)]
    rows[6][4] = "n/a"
    path = write_csv(tmp_path / "log.csv", IMU_HEADER, rows)
    cmap = ColumnMap.from_dict(IMU_MAP)
    with pytest.raises(CsvImportError, match=r"log.csv line 8: column 'ax' \(imu.linear_acceleration.x\) is 'n/a'"):
        import_csv(path, cmap, tmp_path / "strict")
    assert sum(1 for _ in BagReader(tmp_path / "strict").messages()) == 6  # what came before is kept
    report = import_csv(path, ColumnMap.from_dict(IMU_MAP), tmp_path / "lenient", skip_bad_rows=True)
    assert report.rows == 9 and report.skipped_rows == {"bad cell": 1}


def test_rows_whose_time_does_not_increase_are_skipped_counted_and_logged_once(tmp_path: Path, caplog) -> None:
    times = [0.0, 0.001, 0.002, 0.0015, 0.002, 0.003, 0.001, 0.004]
    path = write_csv(tmp_path / "log.csv", IMU_HEADER, [[t, 0, 0, 0, 0, 0, 9.81] for t in times])
    with caplog.at_level(logging.WARNING, logger="tal.csv_import"):
        report = import_csv(path, ColumnMap.from_dict(IMU_MAP), tmp_path / "bag")
    assert report.rows == 5 and report.skipped_rows == {"time not increasing": 3}
    assert len(caplog.records) == 1 and "log.csv line 5" in caplog.records[0].getMessage()
    stamps = [m.log_time_ns for m in BagReader(tmp_path / "bag").messages()]
    assert stamps == [0, 1_000_000, 2_000_000, 3_000_000, 4_000_000]


@pytest.mark.parametrize(("raw", "match"), [
    ({"imu": IMU_MAP["imu"]}, "the map needs 'time'"),
    ({"time": {"column": "t", "unit": "s"}}, "maps no signal"),
    ({**IMU_MAP, "imu": {"angular_velocity": {"x": {"column": "gx", "unit": "rad/s"}}}}, r"missing \['y', 'z'\]"),
    ({**IMU_MAP, "time": {"column": "t", "unit": "s", "scale": 0}}, "scale 0; it must be a finite non-zero"),
    ({**IMU_MAP, "joint_states": {"joints": ["a", "a"], "position": {"column": "q_{joint}", "unit": "rad"}}},
     "must be unique names"),
])
def test_invalid_maps_are_refused_with_the_reason(raw, match) -> None:
    with pytest.raises(CsvImportError, match=match):
        ColumnMap.from_dict(raw)


def test_a_quaternion_that_is_not_unit_and_an_empty_file_are_refused(tmp_path: Path) -> None:
    header = ["t", "x", "y", "z", "qx", "qy", "qz", "qw"]
    raw = {"time": {"column": "t", "unit": "s"}, "ground_truth": {
        "position": {a: {"column": a, "unit": "m"} for a in "xyz"},
        "orientation_xyzw": {a: {"column": f"q{a}", "unit": "-"} for a in "xyzw"}}}
    path = write_csv(tmp_path / "log.csv", header, [[0.0, 0, 0, 0.5, 0, 0, 0, 1], [0.001, 0, 0, 0.5, 0, 0, 0, 2]])
    with pytest.raises(CsvImportError, match="log.csv line 3: ground_truth.orientation_xyzw has norm 2.000"):
        import_csv(path, ColumnMap.from_dict(raw), tmp_path / "bag")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(CsvImportError, match="empty.csv line 1: the file is empty"):
        import_csv(tmp_path / "empty.csv", ColumnMap.from_dict(raw), tmp_path / "bag2")


def test_a_log_with_foot_force_sensors_and_no_torques_imports_to_foot_contacts(tmp_path: Path) -> None:
    """A Go1-style log: joint positions and velocities (no torques), IMU, raw foot force counts and contact
    flags under the log's own leg names (FR, FL, RR, RL) go to /joint_states and /foot_contacts in tal's leg
    order (LF, RF, LH, RH); exported back in the log's units and columns it reads the same."""
    legs = {"LF": "FL", "RF": "FR", "LH": "RL", "RH": "RR"}
    joints = [f"{leg}_{j}" for leg in legs for j in ("hip", "thigh", "calf")]
    cmap = ColumnMap.from_dict({
        "time": {"column": "stamp", "unit": "s"},
        "joint_states": {"joints": joints, "position": {"column": "q_{joint}", "unit": "rad"},
                         "velocity": {"column": "dq_{joint}", "unit": "rad/s"}},
        "imu": {"angular_velocity": {a: {"column": f"w{a}", "unit": "rad/s"} for a in "xyz"},
                "linear_acceleration": {a: {"column": f"a{a}", "unit": "m/s^2"} for a in "xyz"}},
        "foot_contacts": {"legs": list(legs.values()), "force": {"column": "foot_force_{leg}", "unit": "count"},
                          "in_contact": {"column": "contact_{leg}", "unit": "-"}}})
    header = (["stamp"] + [f"q_{j}" for j in joints] + [f"dq_{j}" for j in joints]
              + [f"w{a}" for a in "xyz"] + [f"a{a}" for a in "xyz"]
              + [f"foot_force_{n}" for n in ("FR", "FL", "RR", "RL")] + [f"contact_{n}" for n in ("FR", "FL", "RR", "RL")])
    rows = []
    for k in range(5):
        force = {"FR": 10 + k, "FL": 200 + k, "RR": 300 + k, "RL": 15 + k}   # counts: FL and RR in stance
        row = {"stamp": 0.002 * k, **{f"q_{j}": 0.1 * i for i, j in enumerate(joints)},
               **{f"dq_{j}": 0.0 for j in joints}, "wx": 0.0, "wy": 0.0, "wz": 0.01, "ax": 0.0, "ay": 0.0,
               "az": 9.81, **{f"foot_force_{n}": f for n, f in force.items()},
               **{f"contact_{n}": int(f > 100) for n, f in force.items()}}
        rows.append([row[h] for h in header])
    log = tmp_path / "go1.csv"
    with log.open("w", newline="") as stream:
        csv.writer(stream).writerows([header, *rows])
    report = import_csv(log, cmap, tmp_path / "bag")
    assert report.rows == 5 and report.messages["/foot_contacts"] == 5 and report.messages["/joint_states"] == 5
    feet = [m.message for m in BagReader(tmp_path / "bag").messages(["/foot_contacts"])]
    assert [f.z for f in feet[2].force] == [202.0, 12.0, 17.0, 302.0]          # LF=FL, RF=FR, LH=RL, RH=RR
    assert list(feet[2].in_contact) == [True, False, False, True]
    joint_states = next(iter(BagReader(tmp_path / "bag").messages(["/joint_states"]))).message
    assert list(joint_states.effort) == [] and list(joint_states.name) == joints
    from tal_estimation.messages import foot_contact_values
    assert foot_contact_values(feet[2], "force_sensor").tolist() == [202.0, 12.0, 17.0, 302.0]
    assert foot_contact_values(feet[2], "contact_flags").tolist() == [1.0, 0.0, 0.0, 1.0]
    assert export_csv(tmp_path / "bag", cmap, tmp_path / "again.csv") == 5
    with (tmp_path / "again.csv").open(newline="") as stream:
        again = list(csv.reader(stream))
    exported = dict(zip(again[0], again[3], strict=True))
    assert float(exported["foot_force_FL"]) == 202.0 and float(exported["contact_FR"]) == 0.0
    with pytest.raises(CsvImportError, match="four distinct names"):
        ColumnMap.from_dict({"time": {"column": "t", "unit": "s"},
                             "foot_contacts": {"legs": ["FL", "FL", "RL", "RR"], "force": {"column": "f", "unit": "N"}}})
    with pytest.raises(CsvImportError, match="not a unit of force"):
        ColumnMap.from_dict({"time": {"column": "t", "unit": "s"},
                             "foot_contacts": {"force": {"column": "f_{leg}", "unit": "kg"}}})


def test_columns_listed_in_the_robots_own_order_import_in_tals_order(tmp_path: Path) -> None:
    """A log whose columns are numbered in the robot's motor and foot order (q_0.., foot_force_0..) maps them
    with explicit ``columns`` lists; a list of the wrong length or given with ``column`` is refused."""
    joints = ["a_joint", "b_joint", "c_joint"]
    raw = {"time": {"column": "stamp", "unit": "s"},
           "joint_states": {"joints": joints, "position": {"columns": ["q_2", "q_0", "q_1"], "unit": "rad"}},
           "foot_contacts": {"force": {"columns": ["ff_1", "ff_0", "ff_3", "ff_2"], "unit": "count"}}}
    header = ["stamp", "q_0", "q_1", "q_2", "ff_0", "ff_1", "ff_2", "ff_3", "unmapped"]
    path = write_csv(tmp_path / "log.csv", header, [[0.0021, 0.1, 0.2, 0.3, 10, 11, 12, 13, 99],
                                                    [0.0039, 0.1, 0.2, 0.3, 20, 21, 22, 23, 99]])
    report = import_csv(path, ColumnMap.from_dict(raw), tmp_path / "bag")
    assert report.rows == 2 and "/joint_states" in report.messages and "/foot_contacts" in report.messages
    js = next(BagReader(tmp_path / "bag").messages(["/joint_states"])).message
    assert list(js.name) == joints and list(js.position) == [0.3, 0.1, 0.2] and list(js.velocity) == []
    feet = [m.message for m in BagReader(tmp_path / "bag").messages(["/foot_contacts"])]
    assert [f.z for f in feet[1].force] == [21.0, 20.0, 23.0, 22.0]     # LF, RF, LH, RH
    stamps = [m.log_time_ns for m in BagReader(tmp_path / "bag").messages(["/foot_contacts"])]
    assert stamps == [2_100_000, 3_900_000]                              # jittered stamps kept as logged
    short = {**raw, "joint_states": {"joints": joints, "position": {"columns": ["q_0", "q_1"], "unit": "rad"}}}
    with pytest.raises(CsvImportError, match=r"joint_states.position.columns must list 3 distinct column names "
                                             r"\(one per joint: a_joint, b_joint, c_joint\)"):
        ColumnMap.from_dict(short)
    both = {**raw, "foot_contacts": {"force": {"column": "f_{leg}", "columns": ["a", "b", "c", "d"], "unit": "N"}}}
    with pytest.raises(CsvImportError, match="gives both 'column' and 'columns'"):
        ColumnMap.from_dict(both)
    cut = write_csv(tmp_path / "cut.csv", header[:-3], [[0.0, 0.1, 0.2, 0.3, 10, 11]])
    with pytest.raises(CsvImportError, match=r"cut.csv line 1: column 'ff_3' \(foot_contacts.force of LH, map "
                                             r"<map>\) is not in the header"):
        import_csv(cut, ColumnMap.from_dict(raw), tmp_path / "bag2")
