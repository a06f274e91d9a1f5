"""rosbag2 MCAP bags written by tal_core.ros.bag_io: read back by our reader and by an independent one
(rosbags), metadata.yaml as rosbag2 writes it, truncated and corrupt files, unknown types."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import pytest
import yaml
from geometry_msgs.msg import Vector3
from mcap.reader import make_reader
from nav_msgs.msg import Odometry
from rosbags.highlevel import AnyReader
from sensor_msgs.msg import Imu, JointState

from tal_core.ros.bag_io import BagError, BagReader, BagWriter, content_digest, exact_cdr, message_definition
from tal_core.ros.node_utils import stamp_from_ns
from tal_msgs.msg import ContactState, TerrainImpedance

MS = 1_000_000


def write_sample_bag(path: Path, n: int = 200, *, flush_every: int = 0) -> dict[str, int]:
    """n ms of a small robot log: imu and joint_states every ms, contacts every 4 ms, impedance every 8."""
    counts = {"/imu": 0, "/joint_states": 0, "/contact_estimate": 0, "/terrain_impedance": 0}
    with BagWriter(path, chunk_size=4096) as bag:
        for k in range(n):
            stamp = stamp_from_ns(k * MS)
            imu = Imu()
            imu.header.stamp = stamp
            imu.linear_acceleration = Vector3(x=0.0, y=0.0, z=9.81 + 0.001 * k)
            bag.write("/imu", imu, k * MS)
            joints = JointState(name=["lf_haa_joint", "lf_hfe_joint"], position=[0.1 * k, -0.2], velocity=[],
                                effort=[1.5, float(k)])
            joints.header.stamp = stamp
            bag.write("/joint_states", joints, k * MS)
            counts["/imu"] += 1
            counts["/joint_states"] += 1
            if k % 4 == 0:
                contact = ContactState()
                contact.header.stamp = stamp
                contact.in_contact[1] = True
                contact.probability[1] = 0.75
                contact.penetration[2] = math.nan
                bag.write("/contact_estimate", contact, k * MS)
                counts["/contact_estimate"] += 1
            if k % 8 == 0:
                impedance = TerrainImpedance()
                impedance.header.stamp = stamp
                impedance.stiffness_normal[0] = 2400.0 + k
                bag.write("/terrain_impedance", impedance, k * MS)
                counts["/terrain_impedance"] += 1
            if flush_every and k % flush_every == flush_every - 1:
                bag.flush()
    return counts


def test_round_trip_with_our_reader(tmp_path: Path) -> None:
    counts = write_sample_bag(tmp_path / "bag")
    reader = BagReader(tmp_path / "bag")
    messages = list(reader.messages())
    assert reader.report.complete and reader.report.counts == counts
    imu = [m for m in messages if m.topic == "/imu"]
    assert [m.log_time_ns for m in imu] == [k * MS for k in range(200)]
    assert imu[57].message.linear_acceleration.z == pytest.approx(9.81 + 0.057)
    assert imu[57].publish_time_ns == 57 * MS  # the header stamp
    contact = next(m for m in messages if m.topic == "/contact_estimate").message
    assert list(contact.in_contact) == [False, True, False, False] and contact.probability[1] == 0.75
    assert math.isnan(contact.penetration[2])
    # Topic selection and a time window.
    window = list(reader.messages(["/joint_states"], start_ns=10 * MS, end_ns=19 * MS))
    assert [m.message.effort[1] for m in window] == [float(k) for k in range(10, 20)]


def test_an_independent_reader_decodes_every_message_and_the_metadata_matches(tmp_path: Path) -> None:
    counts = write_sample_bag(tmp_path / "bag")
    with AnyReader([tmp_path / "bag"]) as reader:
        decoded = 0
        for connection, timestamp, raw in reader.messages():
            message = reader.deserialize(raw, connection.msgtype)
            decoded += 1
            if connection.topic == "/terrain_impedance":
                assert message.stiffness_normal[0] == 2400.0 + timestamp // MS
        assert decoded == sum(counts.values())
        assert {c.topic: c.msgcount for c in reader.connections} == counts
        assert {c.topic: c.msgtype for c in reader.connections}["/contact_estimate"] == "tal_msgs/msg/ContactState"
        assert reader.duration == 199 * MS + 1  # rosbags counts the end inclusively
    info = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["message_count"] == sum(counts.values())
    assert info["duration"]["nanoseconds"] == 199 * MS
    assert info["starting_time"]["nanoseconds_since_epoch"] == 0
    topics = {t["topic_metadata"]["name"]: (t["topic_metadata"]["type"], t["message_count"])
              for t in info["topics_with_message_count"]}
    assert topics["/joint_states"] == ("sensor_msgs/msg/JointState", 200)
    assert info["relative_file_paths"] == ["bag_0.mcap"]
    assert all(t["topic_metadata"]["serialization_format"] == "cdr" for t in info["topics_with_message_count"])


def test_schema_text_carries_the_nested_definitions() -> None:
    text = message_definition("nav_msgs/msg/Odometry")
    for nested in ("std_msgs/msg/Header", "geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/Twist",
                   "geometry_msgs/msg/Vector3", "builtin_interfaces/msg/Time"):
        assert f"MSG: {nested}\n" in text
    assert text.count("MSG: geometry_msgs/msg/Vector3\n") == 1


def test_exact_cdr_drops_the_stale_tail_of_rclpy_serialisation() -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    message = JointState(name=["a", "b"], position=[1.0, 2.0])
    exact = exact_cdr(message)
    assert len(exact) < len(serialize_message(message))  # the estimate over-reports for sequences
    assert list(deserialize_message(exact, JointState).position) == [1.0, 2.0]
    assert len(exact_cdr(Odometry())) == len(serialize_message(Odometry()))  # no sequences: no tail


@pytest.mark.parametrize("keep", [0.5, 0.9])
def test_a_truncated_bag_yields_what_was_flushed_and_says_how_much(tmp_path: Path, keep: float) -> None:
    counts = write_sample_bag(tmp_path / "bag", flush_every=20)
    mcap_file = tmp_path / "bag" / "bag_0.mcap"
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: int(len(data) * keep)])
    (tmp_path / "bag" / "metadata.yaml").unlink()  # as after a SIGKILL: no metadata written
    reader = BagReader(tmp_path / "bag")
    messages = list(reader.messages())
    assert not reader.report.complete
    assert 0 < len(messages) <= sum(counts.values())  # at 90 % only the summary section is lost
    assert f"after {len(messages)} messages" in reader.report.error
    stamps = [m.log_time_ns for m in messages if m.topic == "/imu"]
    assert stamps == [k * MS for k in range(len(stamps))]  # a clean prefix
    with pytest.raises(BagError, match=r"(truncated or corrupt|ends without an MCAP footer) after \d+ messages"):
        list(BagReader(tmp_path / "bag").messages(strict=True))


def test_corrupt_bytes_in_the_middle_stop_the_read_with_a_clear_error(tmp_path: Path) -> None:
    write_sample_bag(tmp_path / "bag", flush_every=20)
    mcap_file = tmp_path / "bag" / "bag_0.mcap"
    # The middle of the middle chunk (the file's middle may fall on an index record the reader does not need:
    # CDR padding bytes are not deterministic, so the chunk sizes vary from run to run).
    with mcap_file.open("rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    chunk = chunks[len(chunks) // 2]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data = bytearray(mcap_file.read_bytes())
    data[middle:middle + 64] = b"\xff" * 64
    mcap_file.write_bytes(bytes(data))
    reader = BagReader(tmp_path / "bag")
    messages = list(reader.messages())
    assert not reader.report.complete and "truncated or corrupt after" in reader.report.error
    assert 0 < len(messages) < 450


def test_unknown_types_are_skipped_with_one_warning_per_type(tmp_path: Path, caplog) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic("/mystery", "acme_msgs/msg/Widget", definition="float64 size\n")
        for k in range(5):
            bag.write("/mystery", b"\x00\x01\x00\x00" + bytes(8), k * MS)
            imu = Imu()
            bag.write("/imu", imu, k * MS)
    with caplog.at_level(logging.WARNING, logger="tal_core.ros.bag_io"):
        reader = BagReader(tmp_path / "bag")
        messages = list(reader.messages())
    assert [m.topic for m in messages] == ["/imu"] * 5
    assert reader.report.skipped_types == {"acme_msgs/msg/Widget"}
    assert sum("acme_msgs/msg/Widget" in r.message for r in caplog.records) == 1
    raw = list(BagReader(tmp_path / "bag").messages(decode=False))
    assert len(raw) == 10  # raw reading keeps them


def test_writer_refuses_bad_requests(tmp_path: Path) -> None:
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(BagError, match="exists and is not empty"):
        BagWriter(tmp_path / "full")
    with pytest.raises(BagError, match="compression must be one of"):
        BagWriter(tmp_path / "a", compression="gzip")
    with BagWriter(tmp_path / "b") as bag:
        bag.write("/imu", Imu(), 0)
        with pytest.raises(BagError, match="already has type sensor_msgs/msg/Imu"):
            bag.write("/imu", JointState(), 1)
        with pytest.raises(BagError, match="undeclared topic"):
            bag.write("/raw", b"\x00", 2)
    with pytest.raises(BagError, match="no bag at"):
        BagReader(tmp_path / "missing")


def test_the_content_digest_ignores_cdr_padding_and_sees_every_field(tmp_path: Path) -> None:
    write_sample_bag(tmp_path / "a", 50)
    write_sample_bag(tmp_path / "b", 50)
    write_sample_bag(tmp_path / "c", 49)
    assert content_digest(tmp_path / "a") == content_digest(tmp_path / "b") != content_digest(tmp_path / "c")
    # The same joint state twice, once with garbage in the alignment padding after the first name (FastCDR
    # does not initialise it): equal content, different bytes, equal digest; a changed value differs.
    joints = JointState(name=["lf_haa_joint", "lf_hfe_joint"], position=[0.1, -0.2], velocity=[], effort=[1.5, 2.0])
    clean = exact_cdr(joints)
    end = clean.index(b"lf_haa_joint\x00") + len(b"lf_haa_joint\x00")
    dirty = clean[:end] + b"\xab\xcd\xef" + clean[end + 3:]
    changed = exact_cdr(JointState(name=joints.name, position=[0.1, -0.25], velocity=[], effort=[1.5, 2.0]))
    for name, data in (("clean", clean), ("dirty", dirty), ("changed", changed)):
        with BagWriter(tmp_path / name) as bag:
            bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
            bag.write("/joint_states", data, MS)
    assert dirty != clean
    assert content_digest(tmp_path / "clean") == content_digest(tmp_path / "dirty")
    assert content_digest(tmp_path / "changed") != content_digest(tmp_path / "clean")
