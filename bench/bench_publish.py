#!/usr/bin/env python3
"""What publishing one message costs the publishing node, by number of reader processes and by Fast DDS setting.

Run after ``source scripts/env.sh``: ``python bench/bench_publish.py [--seconds 6] [--rate-hz 1000]``.

Every node of the tour spends a fifth to a quarter of its CPU in ``Publisher.publish`` (py-spy on the running
graph: wbc 21.7 %, state_estimator 27.3 %, tce 22.0 % self time), although each publishes CDR bytes it wrote
into a template (``tal_core.ros.cdr.CdrTemplate``), so rclpy's message conversion does not run. What is left
is the middleware's write. This bench measures it: a publisher process sends a serialised tal_msgs/GaitState
(the wbc's 250 Hz message, as bytes) at ``--rate-hz`` on the wall clock to 0, 1 or 3 reader processes (raw
subscriptions on rclpy's EventsExecutor, reliable, depth 100, as the graph's), and reports its CPU time
(user + system) per message around ``publish`` alone, and each reader's CPU per message received. Settings
(environment of every process): Fast DDS's defaults, its shared-memory transport only
(``FASTDDS_BUILTIN_TRANSPORTS=SHM``), UDPv4 only, and asynchronous publication
(``RMW_FASTRTPS_PUBLICATION_MODE=ASYNCHRONOUS``: the write moves to a middleware thread of the same process,
so the publisher's whole-process CPU per message, its pacing loop included, is reported too).

Writes ``bench/out/bench_publish.json``; prints a markdown table. Never a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from common import progress_for, write_json

progress = progress_for("bench_publish")
TOPIC = "bench/publish"
SETTINGS = {
    "default": {},
    "shm_only": {"FASTDDS_BUILTIN_TRANSPORTS": "SHM"},
    "udpv4_only": {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"},
    "asynchronous": {"RMW_FASTRTPS_PUBLICATION_MODE": "ASYNCHRONOUS"},
}


def _cpu_s() -> float:
    """CPU time of this process (every thread) [s]."""
    return time.process_time()


def _qos():
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)


def publisher(readers: int, rate_hz: float, seconds: float) -> dict:
    import rclpy
    from rclpy.serialization import serialize_message

    from tal_msgs.msg import GaitState

    rclpy.init()
    node = rclpy.create_node("bench_publish_pub")
    pub = node.create_publisher(GaitState, TOPIC, _qos())
    msg = GaitState(gait="trot")
    msg.header.frame_id = "world"
    data = serialize_message(msg)
    deadline = time.monotonic() + 10.0
    while pub.get_subscription_count() < readers and time.monotonic() < deadline:
        time.sleep(0.05)
    matched = pub.get_subscription_count()
    time.sleep(1.0)  # the readers' discovery of this writer
    period, n, publish_cpu = 1.0 / rate_hz, int(rate_hz * seconds), 0.0
    start, process0 = time.monotonic(), _cpu_s()
    for k in range(n):
        c0 = _cpu_s()
        pub.publish(data)
        publish_cpu += _cpu_s() - c0
        delay = start + (k + 1) * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    time.sleep(1.0)  # let asynchronous writes and the readers finish
    process = _cpu_s() - process0
    node.destroy_node()
    rclpy.shutdown()
    return {"readers_matched": matched, "messages": n, "publish_cpu_us_per_message": 1e6 * publish_cpu / n,
            "process_cpu_us_per_message": 1e6 * process / n}


def reader(seconds: float) -> dict:
    import rclpy
    from rclpy.experimental import EventsExecutor

    from tal_msgs.msg import GaitState

    rclpy.init()
    node = rclpy.create_node(f"bench_publish_sub_{os.getpid()}")
    marks: dict[str, float] = {"count": 0}

    def on_raw(_data: bytes) -> None:
        if marks["count"] == 0:
            marks["cpu0"] = _cpu_s()
        marks["count"] += 1
        marks["cpu1"] = _cpu_s()

    node.create_subscription(GaitState, TOPIC, on_raw, _qos(), raw=True)
    executor = EventsExecutor()
    executor.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()
    count = int(marks["count"])
    cpu = marks.get("cpu1", 0.0) - marks.get("cpu0", 0.0)
    return {"received": count, "cpu_us_per_message": 1e6 * cpu / max(1, count - 1)}


def run(setting: str, readers: int, rate_hz: float, seconds: float) -> dict:
    env = {**os.environ, **SETTINGS[setting], "ROS_DOMAIN_ID": str(os.getpid() % 100 + 100)}
    me = [sys.executable, __file__]
    subs = [subprocess.Popen([*me, "--role", "reader", "--seconds", str(seconds + 14.0)], env=env,
                             stdout=subprocess.PIPE, text=True) for _ in range(readers)]
    pub = subprocess.run([*me, "--role", "publisher", "--readers", str(readers), "--rate-hz", str(rate_hz),
                          "--seconds", str(seconds)], env=env, stdout=subprocess.PIPE, text=True, check=True)
    result = {"setting": setting, "readers": readers, **json.loads(pub.stdout.strip().splitlines()[-1])}
    got = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in subs]
    result["reader_cpu_us_per_message"] = [round(g["cpu_us_per_message"], 1) for g in got]
    result["received"] = [g["received"] for g in got]
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=("bench", "publisher", "reader"), default="bench")
    parser.add_argument("--readers", type=int, default=0)
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    args = parser.parse_args()
    if args.role == "publisher":
        print(json.dumps(publisher(args.readers, args.rate_hz, args.seconds)), flush=True)
        return 0
    if args.role == "reader":
        print(json.dumps(reader(args.seconds)), flush=True)
        return 0
    rows = []
    cases = [("default", 0), ("default", 1), ("default", 3)] + [(s, 3) for s in SETTINGS if s != "default"]
    for i, (setting, readers) in enumerate(cases):
        progress(f"{i + 1}/{len(cases)}: {setting}, {readers} reader(s), {args.seconds:g} s at {args.rate_hz:g} Hz")
        rows.append(run(setting, readers, args.rate_hz, args.seconds))
    write_json("bench_publish", {"rate_hz": args.rate_hz, "seconds": args.seconds, "rows": rows}, log=progress)
    print("| setting | readers | publish CPU per message [us] | publisher process CPU per message [us] "
          "| each reader's CPU per message [us] | received |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['setting']} | {r['readers']} | {r['publish_cpu_us_per_message']:.1f} | "
              f"{r['process_cpu_us_per_message']:.1f} | "
              f"{', '.join(f'{v:g}' for v in r['reader_cpu_us_per_message']) or '-'} | "
              f"{', '.join(str(v) for v in r['received']) or '-'} of {r['messages']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
