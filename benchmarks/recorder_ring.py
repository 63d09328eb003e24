"""What the Recorder's ring costs over the cheapest way to hold the same messages, and what writing a window costs.

Receivers, each in a process of its own, in turns, fed by one publisher process (a ROS domain of this run's
own, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST): /bench/odom (nav_msgs/Odometry) at --odom-hz and
/bench/image (sensor_msgs/Image, 640x480 bgr8, 921,600 bytes of pixels) at --fps, paced on the wall clock.

1. ``bare``: raw (serialised) subscriptions taken by DC's intake loop (the measurement server's receive
   path), the callback appending the bytes to a list — the cheapest way to do the job in Python;
2. ``ring``: the same subscriptions, the callback the Recorder's (a counter, then Ring.append with the
   receive and source times of the message info), ``pre_trigger`` --pre seconds, ``max_memory_mb`` --mb.

Each receiver's CPU (utime+stime of /proc/self/stat) is taken over --seconds after a warm-up, with the
messages and bytes it received in that time. Then, in this process, a window of the same messages (from a
ring filled here) is written with the Recorder's writer (write_mcap: schemas, lz4/zstd/none) and with
mcap's Writer alone (no compression, one schema): CPU per MB written.

    .venv/bin/python benchmarks/recorder_ring.py [--seconds 10] [--odom-hz 1000] [--fps 30] [--runs 1]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

CHILD = r"""
import json, os, sys, time, functools
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image
from dc_core.intake import Intake
from dc_measurements.recorder.ring import Ring

kind = sys.argv[1]
seconds, warmup, pre, mb = (float(a) for a in sys.argv[2:6])
rclpy.init()
node = rclpy.create_node("bench_recorder_" + kind)
intake = Intake(node)
qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
received = [0, 0]
if kind == "bare":
    kept = []
    def on_message(index, data, info):
        kept.append(data)
        received[index] += 1
else:
    ring = Ring(int(mb * 1024 * 1024), int(pre * 1e9), 2)
    def on_message(index, data, info):
        received[index] += 1
        ring.append(info["received_timestamp"], info["source_timestamp"], index, data, False)
for index, (msg_type, topic) in enumerate(((Odometry, "/bench/odom"), (Image, "/bench/image"))):
    intake.subscribe(msg_type, topic, functools.partial(on_message, index), qos, raw=True)
print("ready", flush=True)
def cpu():
    fields = open("/proc/self/stat").read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
start = time.monotonic()
while time.monotonic() - start < warmup:
    intake.take(0.1)
counted, cpu0, t0 = list(received), cpu(), time.monotonic()
while time.monotonic() - t0 < seconds:
    intake.take(0.1)
elapsed, used = time.monotonic() - t0, cpu() - cpu0
out = {"kind": kind, "seconds": elapsed, "cpu_s": used}
out.update(odom=received[0] - counted[0], images=received[1] - counted[1])
if kind == "ring":
    out["ring_mb"] = ring.bytes / 2**20
    out["lost_to_bound"] = sum(ring.lost_to_bound)
print(json.dumps(out), flush=True)
"""

PUBLISHER = r"""
import sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image
odom_hz, fps, seconds = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
rclpy.init()
node = rclpy.create_node("bench_recorder_publisher")
qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
odom_pub = node.create_publisher(Odometry, "/bench/odom", qos)
image_pub = node.create_publisher(Image, "/bench/image", qos)
image = Image(height=480, width=640, encoding="bgr8", step=1920, data=bytes(640 * 480 * 3))
odom = Odometry()
start = time.monotonic()
sent_odom = sent_images = 0
try:
    while time.monotonic() - start < seconds:
        now = time.monotonic() - start
        while sent_odom < now * odom_hz:
            odom.pose.pose.position.x = float(sent_odom)
            odom_pub.publish(odom)
            sent_odom += 1
        while sent_images < now * fps:
            image_pub.publish(image)
            sent_images += 1
        time.sleep(0.001)
except Exception:  # stopped with SIGTERM once the receiver is done: rclpy's context is gone
    pass
"""


def run_receiver(kind: str, args: argparse.Namespace, env: dict[str, str]) -> dict[str, Any]:
    warmup = 3.0
    receiver = subprocess.Popen(
        [sys.executable, "-c", CHILD, kind, str(args.seconds), str(warmup), str(args.pre), str(args.mb)],
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert receiver.stdout is not None
    assert receiver.stdout.readline().strip() == "ready"
    publisher = subprocess.Popen(
        [sys.executable, "-c", PUBLISHER, str(args.odom_hz), str(args.fps), str(args.seconds + warmup + 5)], env=env
    )
    try:
        line = receiver.stdout.readline()
        receiver.wait(30)
    finally:
        for child in (publisher, receiver):
            child.terminate()
            try:
                child.wait(10)
            except subprocess.TimeoutExpired:
                child.kill()
    result: dict[str, Any] = json.loads(line)
    mb = (result["odom"] * 725 + result["images"] * (921_600 + 100)) / 2**20  # serialised sizes, measured
    result["cpu_ms_per_1000_messages"] = 1000 * result["cpu_s"] / max(1, result["odom"] + result["images"]) * 1000
    result["cpu_ms_per_mb"] = 1000 * result["cpu_s"] / max(mb, 1e-9)
    result["cpu_percent"] = 100 * result["cpu_s"] / result["seconds"]
    return result


def writers(seconds_of_data: float, odom_hz: float, fps: float) -> list[dict[str, Any]]:
    from mcap.writer import CompressionType, Writer

    from dc_measurements.recorder.definitions import Definitions
    from dc_measurements.recorder.mcap_file import Channel, write_mcap
    from dc_measurements.recorder.ring import Entry

    rng = random.Random(1)
    odom = rng.randbytes(725)
    image = bytes(921_700)  # a camera's frame compresses: zeros are its best case, random bytes its worst
    entries: list[Entry] = []
    for i in range(int(seconds_of_data * odom_hz)):
        entries.append((i * int(1e9 / odom_hz), 0, 0, odom))
    for i in range(int(seconds_of_data * fps)):
        entries.append((i * int(1e9 / fps), 0, 1, image))
    total_mb = sum(len(e[3]) for e in entries) / 2**20
    channels: list[Channel | None] = [
        Channel("/bench/odom", "nav_msgs/msg/Odometry"),
        Channel("/bench/image", "sensor_msgs/msg/Image"),
    ]
    definitions = Definitions()
    definitions.get("nav_msgs/msg/Odometry"), definitions.get("sensor_msgs/msg/Image")  # parsed once, not timed
    results = []
    with tempfile.TemporaryDirectory() as folder:
        for compression in ("none", "lz4", "zstd"):
            t0 = time.process_time()
            written = write_mcap(f"{folder}/w.mcap", channels, entries, compression, definitions.get)
            results.append(
                {
                    "writer": f"write_mcap {compression}",
                    "cpu_ms_per_mb": 1000 * (time.process_time() - t0) / total_mb,
                    "file_mb": written.size / 2**20,
                }
            )
        t0 = time.process_time()
        with open(f"{folder}/bare.mcap", "wb") as stream:
            writer = Writer(stream, compression=CompressionType.NONE)
            writer.start(profile="ros2", library="bench")
            schema = writer.register_schema("x", "ros2msg", b"")
            ids = [writer.register_channel(t, "cdr", schema) for t in ("/bench/odom", "/bench/image")]
            for receive_ns, _, topic, data in entries:
                writer.add_message(ids[topic], receive_ns, data, receive_ns)
            writer.finish()
        results.append(
            {"writer": "mcap Writer alone, none", "cpu_ms_per_mb": 1000 * (time.process_time() - t0) / total_mb}
        )
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--odom-hz", type=float, default=1000.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--pre", type=float, default=10.0, help="the ring's pre_trigger")
    parser.add_argument("--mb", type=float, default=512.0, help="the ring's max_memory_mb")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random.randint(100, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONPATH"] = str(Path(__file__).resolve().parent.parent)
    rows = []
    for _ in range(args.runs):
        for kind in ("bare", "ring"):
            rows.append(run_receiver(kind, args, env))
            print(json.dumps(rows[-1]))
    write_rows = writers(2.0, args.odom_hz, args.fps)
    for row in write_rows:
        print(json.dumps(row))
    bare = [r for r in rows if r["kind"] == "bare"]
    ring = [r for r in rows if r["kind"] == "ring"]

    def per_message(runs: list[dict[str, Any]]) -> float:
        return sum(r["cpu_s"] for r in runs) / max(1, sum(r["odom"] + r["images"] for r in runs))

    ratio = per_message(ring) / max(1e-12, per_message(bare))
    print(f"ring / bare CPU per message: {ratio:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"receivers": rows, "writers": write_rows, "ring_over_bare": ratio}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
