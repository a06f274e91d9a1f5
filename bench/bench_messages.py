#!/usr/bin/env python3
"""What one 1 kHz topic costs a subscribing node, by executor and by how the node takes its messages.

Run after ``source scripts/env.sh``: ``python bench/bench_messages.py [--seconds 8] [--rate-hz 1000]``.

A publisher process sends sensor_msgs/JointState (HyQ's 12 joints, positions, velocities, efforts) at
``--rate-hz`` on the wall clock; a subscriber process spins one node for ``--seconds`` and reports its own
CPU time (user + system, ``resource.getrusage``) per second of wall time, i.e. the share of one core the
topic costs it. Variants of the subscriber:

- ``single``: rclpy's SingleThreadedExecutor, every message deserialised into a Python message;
- ``events``: rclpy's EventsExecutor (rclpy.experimental), every message deserialised;
- ``events_raw_peek``: EventsExecutor, raw CDR bytes; the header stamp read from the bytes
  (``tal_core.ros.cdr.stamp_ns_of``) and only one message in four (a 250 Hz control tick) deserialised.
- ``single_raw_peek``: the same on the SingleThreadedExecutor.
- ``events_view``: EventsExecutor, raw CDR bytes, every message read in place (``tal_core.ros.cdr.CdrReader``
  and ``tal_core.ros.conversions.JointStateReader``: the canonical arrays, no Python message built), as the
  nodes take their inputs.

Then, in one process without DDS, the time to decode one message of each type the nodes take at the control
rate or above into what a node uses (canonical joint arrays, a base state, the IMU vectors, flags and
impedance arrays): ``rclpy.serialization.deserialize_message`` and the message conversion against
``CdrReader.read`` and the view conversion (median of 5 runs of 2,000).

Writes ``bench/out/bench_messages.json``; prints a markdown table. Never a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

from common import progress_for, write_json

progress = progress_for("bench_messages")
VARIANTS = ("single", "events", "single_raw_peek", "events_raw_peek", "events_view")
NAMES = [f"{leg}_{joint}" for leg in ("lf", "rf", "lh", "rh") for joint in ("haa_joint", "hfe_joint", "kfe_joint")]


def publisher(rate_hz: float, seconds: float) -> None:
    import rclpy
    from sensor_msgs.msg import JointState

    from tal_core.ros.node_utils import stamp_from_ns

    rclpy.init()
    node = rclpy.create_node("bench_messages_pub")
    pub = node.create_publisher(JointState, "bench/joint_states", 50)
    msg = JointState(name=NAMES, position=[0.1] * 12, velocity=[0.2] * 12, effort=[0.3] * 12)
    period = 1.0 / rate_hz
    start = time.monotonic()
    k = 0
    while time.monotonic() - start < seconds:
        msg.header.stamp = stamp_from_ns(k * 1_000_000)
        pub.publish(msg)
        k += 1
        delay = start + k * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    node.destroy_node()
    rclpy.shutdown()


def subscriber(variant: str, seconds: float) -> dict:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.experimental import EventsExecutor
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    from tal_core.ros.cdr import stamp_ns_of

    rclpy.init()
    node = rclpy.create_node("bench_messages_sub")
    counts = {"received": 0, "deserialised": 0}

    def on_message(msg: JointState) -> None:
        counts["received"] += 1
        counts["deserialised"] += 1
        _ = msg.position[0]

    def on_raw(data: bytes) -> None:
        counts["received"] += 1
        if stamp_ns_of(data) % 4_000_000 == 0:
            msg = deserialize_message(data, JointState)
            counts["deserialised"] += 1
            _ = msg.position[0]

    from tal_core.ros.cdr import CdrReader
    from tal_core.ros.conversions import JointStateReader

    reader, arrays = CdrReader(JointState), JointStateReader({name: i for i, name in enumerate(NAMES)}, efforts=True)

    def on_view(data: bytes) -> None:
        counts["received"] += 1
        counts["deserialised"] += 1
        _ = arrays(reader.read(data))[0][0]

    raw = variant.endswith("raw_peek") or variant.endswith("view")
    callback = on_view if variant.endswith("view") else on_raw if raw else on_message
    node.create_subscription(JointState, "bench/joint_states", callback, 50, raw=raw)
    executor = EventsExecutor() if variant.startswith("events") else SingleThreadedExecutor()
    executor.add_node(node)
    # Discovery and the first messages before the clock starts.
    deadline = time.monotonic() + 3.0
    while counts["received"] < 10 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    counts["received"] = counts["deserialised"] = 0
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    while time.monotonic() - t0 < seconds:
        executor.spin_once(timeout_sec=0.05)
    r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    wall = t1 - t0
    return {"variant": variant, "wall_s": wall, "cpu_s": cpu, "cpu_share_of_one_core": cpu / wall,
            "messages_per_s": counts["received"] / wall, "deserialised_per_s": counts["deserialised"] / wall,
            "cpu_us_per_message": 1e6 * cpu / max(1, counts["received"])}


def decode_times(repeats: int = 2000) -> list[dict]:
    """[us] per message: deserialise into a Python message vs read in place, for the graph's hot inputs."""
    import numpy as np
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Imu, JointState

    from tal_core.ros.cdr import CdrReader
    from tal_core.ros.conversions import JointStateReader, base_state_from_odometry, base_state_from_odometry_view
    from tal_estimation.messages import joint_state_arrays
    from tal_msgs.msg import ContactState, TerrainImpedance

    odometry = Odometry(child_frame_id="base")
    odometry.header.frame_id = "world"
    odometry.pose.pose.orientation.w = 1.0
    index = {name: i for i, name in enumerate(NAMES)}
    joints = JointStateReader(index, efforts=True)
    cases = [  # (type, message, what a node reads from a Python message, what it reads from a view)
        ("sensor_msgs/JointState (12 joints)", JointState(name=NAMES, position=[0.1] * 12, velocity=[0.2] * 12,
                                                          effort=[0.3] * 12),
         lambda m: joint_state_arrays(m, index), joints),
        ("sensor_msgs/Imu", Imu(),
         lambda m: (np.array([m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]),
                    np.array([m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z])),
         lambda v: (v.vector("linear_acceleration").copy(), v.vector("angular_velocity").copy())),
        ("nav_msgs/Odometry", odometry, base_state_from_odometry, base_state_from_odometry_view),
        ("tal_msgs/ContactState", ContactState(), lambda m: np.array(m.in_contact, dtype=bool),
         lambda v: v.array("in_contact").astype(bool)),
        ("tal_msgs/TerrainImpedance", TerrainImpedance(),
         lambda m: (np.array(m.stiffness_normal, float), np.array(m.valid, bool),
                    np.array([[n.x, n.y, n.z] for n in m.normal], float)),
         lambda v: (v.array("stiffness_normal").astype(float), v.array("valid").astype(bool), v.vectors("normal"))),
    ]
    rows = []
    for name, msg, use_message, use in cases:
        data, reader, msg_type = serialize_message(msg), CdrReader(type(msg)), type(msg)
        times = {"deserialise": [], "in_place": []}
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(repeats):
                use_message(deserialize_message(data, msg_type))
            t1 = time.perf_counter()
            for _ in range(repeats):
                use(reader.read(data))
            t2 = time.perf_counter()
            times["deserialise"].append(1e6 * (t1 - t0) / repeats)
            times["in_place"].append(1e6 * (t2 - t1) / repeats)
        rows.append({"message": name, "deserialise_us": float(np.median(times["deserialise"])),
                     "in_place_us": float(np.median(times["in_place"]))})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    parser.add_argument("--role", choices=("publisher", "subscriber"), help=argparse.SUPPRESS)
    parser.add_argument("--variant", choices=VARIANTS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "publisher":
        publisher(args.rate_hz, args.seconds)
        return 0
    if args.role == "subscriber":
        print(json.dumps(subscriber(args.variant, args.seconds)))
        return 0
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 60))
    results = []
    for variant in VARIANTS:
        progress(f"{variant}: {args.seconds} s at {args.rate_hz:.0f} Hz")
        pub = subprocess.Popen([sys.executable, __file__, "--role", "publisher", "--seconds",
                                str(args.seconds + 6.0), "--rate-hz", str(args.rate_hz)], env=env)
        try:
            out = subprocess.run([sys.executable, __file__, "--role", "subscriber", "--variant", variant,
                                  "--seconds", str(args.seconds)], env=env, capture_output=True, text=True,
                                 check=True).stdout
        finally:
            pub.wait()
        results.append(json.loads(out.strip().splitlines()[-1]))
    progress("decoding in one process")
    decode = decode_times()
    print("| message | deserialise + convert [us] | read in place + convert [us] | ratio |")
    print("|---|---|---|---|")
    for row in decode:
        print(f"| {row['message']} | {row['deserialise_us']:.1f} | {row['in_place_us']:.1f} | "
              f"{row['deserialise_us'] / row['in_place_us']:.1f}x |")
    print()
    print("| subscriber | messages/s | deserialised/s | CPU share of one core | CPU per message [us] |")
    print("|---|---|---|---|---|")
    for r in results:
        print(f"| {r['variant']} | {r['messages_per_s']:.0f} | {r['deserialised_per_s']:.0f} | "
              f"{r['cpu_share_of_one_core']:.3f} | {r['cpu_us_per_message']:.1f} |")
    write_json("bench_messages", {"rate_hz": args.rate_hz, "seconds": args.seconds, "results": results,
                                  "decode": decode},
               log=progress)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
