"""Memory stays flat in the length of a bag: writing and reading stream, nothing accumulates per message."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

CHILD = r"""
import json, sys
import numpy as np
from sensor_msgs.msg import Imu, JointState
from tal_core.ros.bag_io import BagReader, BagWriter, exact_cdr
from tal_msgs.msg import HeightMap

def rss_mb():  # VmHWM: ru_maxrss would carry the parent's (pytest's) peak across fork and exec
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0

case, seconds, path = sys.argv[1], float(sys.argv[2]), sys.argv[3]
rng = np.random.default_rng(0)
pool = {"/imu": [], "/joint_states": [], "/terrain/heightmap": []}
for _ in range(200):
    imu = Imu()
    imu.linear_acceleration.z = float(rng.normal())
    pool["/imu"].append(exact_cdr(imu))
    pool["/joint_states"].append(exact_cdr(JointState(name=[f"j{i}" for i in range(12)],
                                                      position=rng.normal(size=12).tolist())))
    grid = HeightMap(rows=33, cols=33)
    grid.heights = rng.normal(size=33 * 33).astype(np.float32)
    pool["/terrain/heightmap"].append(exact_cdr(grid))
before = rss_mb()
count = payload = 0
if case == "write":
    with BagWriter(path) as bag:
        bag.add_topic("/imu", "sensor_msgs/msg/Imu")
        bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
        bag.add_topic("/terrain/heightmap", "tal_msgs/msg/HeightMap")
        for step in range(int(seconds * 1000)):
            for topic in ("/imu", "/joint_states"):
                bag.write(topic, pool[topic][step % 200], step * 10**6)
                count += 1
                payload += len(pool[topic][step % 200])
            if step % 50 == 0:
                bag.write("/terrain/heightmap", pool["/terrain/heightmap"][step % 200], step * 10**6)
                count += 1
                payload += len(pool["/terrain/heightmap"][step % 200])
else:
    for message in BagReader(path).messages():
        count += 1
        payload += len(message.data)
print(json.dumps({"growth_mb": rss_mb() - before, "peak_mb": rss_mb(), "messages": count, "payload_mb": payload / 1e6}))
"""


def run_child(case: str, seconds: float, path: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, case, str(seconds), str(path)], check=True,
                         capture_output=True, text=True, timeout=300)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_writing_and_reading_a_ten_times_longer_bag_needs_no_more_memory(tmp_path: Path) -> None:
    short, long = tmp_path / "short", tmp_path / "long"
    written = {name: run_child("write", seconds, path) for name, seconds, path in
               (("short", 4.0, short), ("long", 40.0, long))}
    read = {name: run_child("read", 0.0, path) for name, path in (("short", short), ("long", long))}
    assert written["long"]["messages"] == 10 * written["short"]["messages"] == read["long"]["messages"]
    assert written["long"]["payload_mb"] == pytest.approx(read["long"]["payload_mb"])
    assert read["long"]["payload_mb"] > 20.0  # holding it (or its decoded messages) would show
    # Peak resident memory grows by what the chunk buffers need, not with the bag: a 10x longer bag may
    # add at most 1.2x the short bag's growth plus 4 MB of allocator noise.
    for stage in (written, read):
        assert stage["long"]["growth_mb"] <= 1.2 * stage["short"]["growth_mb"] + 4.0, stage
