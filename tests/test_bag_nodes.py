"""bag_recorder and bag_player in real graphs: recording a lockstep run of the simulated robot, replaying
it into a probe, and the recorder as its own process surviving SIGTERM (clean bag) and SIGKILL (at most
the last second lost, the rest readable)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rosbags.highlevel import AnyReader
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64

from tal_control.stand_controller_node import StandControllerNode
from tal_core.ros.bag_io import BagReader
from tal_sim_bridge.bag_player_node import BagPlayerNode
from tal_sim_bridge.bag_recorder_node import BagRecorderNode
from tal_sim_bridge.sim_bridge_node import SimBridgeNode

pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parents[1]
RECORDER = ROOT / "ros2_ws" / "install" / "tal_sim_bridge" / "lib" / "tal_sim_bridge" / "bag_recorder"


def record_lockstep_run(context, spin_until, bag: Path) -> dict:
    bridge = SimBridgeNode(context=context, parameter_overrides=[Parameter("duration_s", value=1.0)])
    controller = StandControllerNode(context=context)
    recorder = BagRecorderNode(context=context, parameter_overrides=[
        Parameter("output", value=str(bag)), Parameter("use_sim_time", value=True),
        Parameter("topics", value=["joint_states", "imu", "ground_truth/odom", "joint_command", "clock"])])
    executor = SingleThreadedExecutor(context=context)
    nodes = (recorder, bridge, controller)
    for node in nodes:
        executor.add_node(node)
    try:
        # The recorder subscribes once it has discovered the topics: start the run after that.
        assert spin_until(executor, lambda: len(recorder._subscribed) == 5, 20.0), recorder._subscribed
        bridge_start = time.monotonic()
        assert spin_until(executor, lambda: bridge.finished, 120.0)
        spin_until(executor, lambda: False, 0.5)
        assert time.monotonic() > bridge_start
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
    return bridge.final_summary


def test_recorder_records_a_lockstep_run_that_an_independent_reader_decodes(context, spin_until, tmp_path) -> None:
    summary = record_lockstep_run(context, spin_until, tmp_path / "bag")
    assert summary["lockstep_timeouts"] == 0
    with AnyReader([tmp_path / "bag"]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        decoded = sum(1 for c, _, raw in reader.messages() if reader.deserialize(raw, c.msgtype) is not None)
    assert decoded == sum(counts.values())
    # 1 kHz sensors for 1 s (the initial state and its re-sends may come on top), 250 Hz ground truth, clock
    # and commands.
    extra = 1 + summary["initial_state_repeats"]
    for topic, rate in (("/joint_states", 1000), ("/imu", 1000), ("/ground_truth/odom", 250), ("/clock", 250)):
        assert rate <= counts[topic] <= rate + extra, (topic, counts[topic])
    assert 250 <= counts["/joint_command"] <= 252
    joints = [m.message for m in BagReader(tmp_path / "bag").messages(["/joint_states"])]
    assert len(joints[-1].name) == 12 and joints[-1].header.stamp.sec == 1


def test_player_replays_every_message_with_clock_and_remapping(context, spin_until, tmp_path) -> None:
    record_lockstep_run(context, spin_until, tmp_path / "bag")
    reader = BagReader(tmp_path / "bag")
    recorded = {}
    for message in reader.messages(decode=False):
        recorded[message.topic] = recorded.get(message.topic, 0) + 1
    probe = rclpy.create_node("probe", context=context)
    got = {"joints": 0, "imu": 0, "clock": 0}
    last_clock = []
    probe.create_subscription(JointState, "replayed/joint_states", lambda m: got.__setitem__(
        "joints", got["joints"] + 1), 2000)
    probe.create_subscription(Imu, "imu", lambda m: got.__setitem__("imu", got["imu"] + 1), 2000)
    probe.create_subscription(ClockMsg, "clock", lambda m: last_clock.append(m.clock.sec + m.clock.nanosec * 1e-9),
                              2000)
    player = BagPlayerNode(context=context, parameter_overrides=[
        Parameter("bag", value=str(tmp_path / "bag")), Parameter("rate", value=4.0),
        Parameter("topics", value=["/joint_states", "/imu", "/clock"]),
        Parameter("remap", value=["/joint_states:=/replayed/joint_states"])])
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    executor.add_node(player)
    try:
        # Play the bag to its end (1 s of recorded time at 4x), then let the last messages arrive.
        assert spin_until(executor, lambda: player.finished, 60.0)
        spin_until(executor, lambda: got["imu"] >= recorded["/imu"] and got["joints"] >= recorded["/joint_states"],
                   5.0)
    finally:
        executor.shutdown()
        player.destroy_node()
        probe.destroy_node()
    assert player.published == recorded["/joint_states"] + recorded["/imu"]  # clock: from the log times
    assert got["joints"] >= recorded["/joint_states"] - 5 and got["imu"] >= recorded["/imu"] - 5
    # Recorded under use_sim_time: the log times, and so the replayed clock, are the run's sim time.
    assert last_clock and max(last_clock) == pytest.approx(1.0, abs=0.01) and min(last_clock) < 0.01


def _recorder_process(bag: Path, log: Path) -> subprocess.Popen:
    env = dict(os.environ)
    return subprocess.Popen([str(RECORDER), "--ros-args", "-p", f"output:={bag}", "-p", "topics:=['/level']",
                             "-p", "flush_period_s:=0.5"], stdout=log.open("w"), stderr=subprocess.STDOUT,
                            env=env, start_new_session=True)


def _publish_for(context, seconds: float, rate_hz: float = 500.0) -> int:
    """Publish std_msgs/Float64 on /level at rate_hz for `seconds` once the recorder is matched."""
    node = rclpy.create_node("level_source", context=context)
    publisher = node.create_publisher(Float64, "/level", 1000)
    deadline = time.monotonic() + 20.0
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert publisher.get_subscription_count() >= 1, "the recorder never subscribed"
    sent = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        publisher.publish(Float64(data=float(sent)))
        sent += 1
        time.sleep(1.0 / rate_hz)
    node.destroy_node()
    return sent


@pytest.mark.skipif(not RECORDER.exists(), reason="workspace not built")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_recorder_process_closes_the_bag_on_sigint_and_sigterm(context, tmp_path, sig) -> None:
    process = _recorder_process(tmp_path / "bag", tmp_path / "recorder.log")
    try:
        sent = _publish_for(context, 1.5)
        time.sleep(0.5)
        process.send_signal(sig)
        assert process.wait(timeout=20) == 0, (tmp_path / "recorder.log").read_text()
    finally:
        if process.poll() is None:
            process.kill()
    assert (tmp_path / "bag" / "metadata.yaml").is_file()
    reader = BagReader(tmp_path / "bag")
    values = [m.message.data for m in reader.messages()]
    assert reader.report.complete
    assert len(values) >= sent - 2 and values == [float(k) for k in range(len(values))]


@pytest.mark.skipif(not RECORDER.exists(), reason="workspace not built")
def test_recorder_killed_with_sigkill_loses_at_most_the_last_flush_period(context, tmp_path) -> None:
    process = _recorder_process(tmp_path / "bag", tmp_path / "recorder.log")
    try:
        rate = 500.0
        sent = _publish_for(context, 2.0, rate)
        time.sleep(0.1)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
    assert not (tmp_path / "bag" / "metadata.yaml").exists()
    reader = BagReader(tmp_path / "bag")
    values = [m.message.data for m in reader.messages()]
    assert not reader.report.complete and "messages" in reader.report.error
    assert values == [float(k) for k in range(len(values))]  # a clean prefix
    # Flushes every 0.5 s: at most about 0.6 s of messages may be lost (well under the 1 s allowed).
    assert len(values) >= sent - 0.6 * rate * 1.5, (len(values), sent)
