"""Trot datasets (make datasets): small versions generated here, deterministic, complete and replayable."""

from __future__ import annotations

import struct

import pytest
import yaml
from tal_lab.datasets import SCENARIOS, DatasetError, generate_all
from tal_lab.estimation_replay import replay_bag

from tal_core.robot_model import RobotModel
from tal_core.ros.bag_io import BagReader, BagWriter

pytestmark = pytest.mark.slow
DURATION_S = 1.0


@pytest.fixture(scope="module")
def twice(tmp_path_factory):
    """The rigid trot-in-place dataset generated twice from the same seed."""
    roots = [tmp_path_factory.mktemp(f"data{i}") for i in range(2)]
    manifests = [generate_all(root, DURATION_S, ["trot_in_place_rigid"], seed=3, progress=False) for root in roots]
    return roots, [yaml.safe_load(m.read_text()) for m in manifests]


def test_the_same_scenario_and_seed_give_the_same_bytes(twice):
    _, manifests = twice
    first, second = (m["datasets"][0] for m in manifests)
    assert first["content_sha256"] == second["content_sha256"]
    assert first["message_counts"] == second["message_counts"]


def test_the_manifest_and_the_bag_hold_every_stream_at_its_rate(twice):
    roots, manifests = twice
    entry = manifests[0]["datasets"][0]
    assert entry["name"] == "trot_in_place_rigid" and entry["seed"] == 3 and entry["duration_s"] == DURATION_S
    assert entry["course"] == "flat_rigid" and entry["imu_noise"]["gyro_std_rad_s"] > 0.0
    counts = entry["message_counts"]
    steps = round(DURATION_S * 1000)
    assert counts["/joint_states"] == counts["/imu"] == counts["/ground_truth/odom"] == steps + 1
    assert counts["/joint_command"] == steps // 4
    assert counts["/ground_truth/contacts"] == steps // 4 + 1
    assert counts["/terrain/heightmap"] == steps // 50 + 1 and counts["/cmd_vel"] == steps // 100 + 1
    reader = BagReader(roots[0] / entry["bag"])
    per_topic: dict[str, int] = {}
    last_stamp = -1
    for message in reader.messages(["/joint_states"]):
        stamp = message.message.header.stamp.sec * 10**9 + message.message.header.stamp.nanosec
        assert stamp == message.log_time_ns and stamp > last_stamp
        last_stamp = stamp
    for message in reader.messages():
        per_topic[message.topic] = per_topic.get(message.topic, 0) + 1
    assert per_topic == counts and reader.report.complete


def test_the_estimator_replays_a_dataset_against_its_ground_truth(twice):
    roots, manifests = twice
    _, summary = replay_bag(roots[0] / manifests[0]["datasets"][0]["bag"], RobotModel.from_name("hyq"),
                            leg_odometry="terrain_aware")
    assert summary["counts"]["ticks"] == 333 and summary["counts"]["rejected"] == 0
    truth = summary["vs_ground_truth"]
    assert truth["samples"] == 333
    assert max(abs(v) for v in truth["final_drift_m"]) < 0.01  # 1 s of trotting in place on rigid ground


def test_the_replay_counts_unreadable_records_and_goes_on(twice, tmp_path):
    """The replay reads records in place (as the nodes do): a truncated IMU and joint-state record and a
    ground truth with a NaN are counted per topic, and every other record is replayed."""
    roots, manifests = twice
    source = BagReader(roots[0] / manifests[0]["datasets"][0]["bag"])
    broken = {"/imu": 100, "/joint_states": 200, "/ground_truth/odom": 300}   # topic -> index of the bad record
    seen: dict[str, int] = {}
    with BagWriter(tmp_path / "bag") as writer:
        for topic, type_name in source.topics().items():
            writer.add_topic(topic, type_name)
        for message in source.messages(decode=False):
            index = seen[message.topic] = seen.get(message.topic, -1) + 1
            data = message.data
            if broken.get(message.topic) == index:
                if message.topic == "/ground_truth/odom":   # position.x NaN: 85 float64 from the end
                    at = len(data) - 8 * 85
                    data = data[:at] + struct.pack("<d", float("nan")) + data[at + 8:]
                else:
                    data = data[: len(data) // 2]
            writer.write(message.topic, data, message.log_time_ns)
    _, summary = replay_bag(tmp_path / "bag", RobotModel.from_name("hyq"), leg_odometry="terrain_aware")
    counts = summary["counts"]
    assert counts["unreadable"] == {"/imu": 1, "/joint_states": 1, "/ground_truth/odom": 1}
    assert counts["imu_samples"] == counts["joint_samples"] == round(DURATION_S * 1000)
    assert counts["ticks"] >= 332 and summary["vs_ground_truth"]["samples"] >= 331


def test_unknown_dataset_names_are_refused(tmp_path):
    with pytest.raises(DatasetError, match="unknown dataset.*'nope'.*trot_in_place_rigid"):
        generate_all(tmp_path, 1.0, ["nope"])
    assert set(SCENARIOS) == {"trot_in_place_rigid", "trot_in_place_soft", "trot_loop_mixed"}
