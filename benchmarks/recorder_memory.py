"""The Recorder's memory under a raw camera: the measurement server's RSS over time against ``max_memory_mb``.

One publisher process (in this run's own ROS domain, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) sends, paced
on the wall clock, what issue 26 names: /camera/image_raw (sensor_msgs/Image 640x480 bgr8, 921,600 bytes of
pixels) at --fps, /odom (nav_msgs/Odometry) and /tf (tf2_msgs/TFMessage, one transform) at 50 Hz, /scan
(sensor_msgs/LaserScan, 720 ranges and intensities) at 10 Hz: ~28 MB a second, nearly all the camera's.
``dc-bringup`` runs a measurement server with one Recorder of the four topics (--pre, --post, --mb) and a
destination server writing its records to a JSON-lines file, in a temporary folder that is its HOME.

The measurement server's RSS (VmRSS) is read every --every seconds from "DC is up" to the end. After --idle
seconds (the ring full: --pre seconds of the topics are more than --mb) ``dc trigger`` opens a window of
--pre + --post seconds, larger than the bound; the run ends --after seconds after the incident's record is
written. The record (cut_by_memory_bound, per topic messages, lost_to_memory_bound and lost_in_transport: their
sum is what was published in the window) and the RSS samples
go to benchmarks/results/recorder_memory_<date>.json; a summary to stdout: RSS before the topics start,
while idle with the ring full, its peak while the window is open and while its file is written, and after.

    .venv/bin/python benchmarks/recorder_memory.py [--mb 200] [--pre 10] [--post 5] [--idle 30] [--runs 1]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import random
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import footprint as fp  # a sibling script: its process tree and /proc readings

PUBLISHER = r"""
import sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image, LaserScan
from tf2_msgs.msg import TFMessage
from geometry_msgs.msg import TransformStamped
fps = float(sys.argv[1])
rclpy.init()
node = rclpy.create_node("bench_recorder_memory_publisher")
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
image = Image(height=480, width=640, encoding="bgr8", step=1920, data=bytes(640 * 480 * 3))
odom = Odometry()
odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
transform = TransformStamped()
transform.header.frame_id, transform.child_frame_id = "odom", "base_link"
tf = TFMessage(transforms=[transform])
scan = LaserScan(angle_increment=0.00873, range_max=12.0, ranges=[1.0] * 720, intensities=[100.0] * 720)
streams = [
    (node.create_publisher(Image, "/camera/image_raw", qos), image, fps),
    (node.create_publisher(Odometry, "/odom", qos), odom, 50.0),
    (node.create_publisher(TFMessage, "/tf", qos), tf, 50.0),
    (node.create_publisher(LaserScan, "/scan", qos), scan, 10.0),
]
sent = [0] * len(streams)
start = time.monotonic()
try:
    while True:
        now = time.monotonic() - start
        for i, (publisher, message, hz) in enumerate(streams):
            while sent[i] < now * hz:
                header = message.transforms[0].header if message is tf else message.header
                header.stamp.sec, header.stamp.nanosec = divmod(time.time_ns(), 1_000_000_000)
                publisher.publish(message)
                sent[i] += 1
        time.sleep(0.002)
except Exception:  # stopped with SIGTERM: rclpy's context is gone
    pass
"""

PARAMS = """\
measurement_server:
  ros__parameters:
    measurement_plugins: ["incidents"]
    save_local_base_path: "var/dc/data/"
    incidents:
      plugin: "dc_measurements/Recorder"
      topics: ["/camera/image_raw", "/odom", "/tf", "/scan"]
      types: ["sensor_msgs/msg/Image", "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage", "sensor_msgs/msg/LaserScan"]
      pre_trigger: {pre}
      post_trigger: {post}
      max_memory_mb: {mb}
      compression: "lz4"
      tags: ["file"]
destination_server:
  ros__parameters:
    flb:
      flush: 1
      storage_path: "var/dc/buffer"
    destination_plugins: ["file"]
    file:
      plugin: "dc_destinations/File"
      path: "var/dc/records"
      file: "incidents.jsonl"
      format: "json"
      inputs: ["/dc/measurement/incidents"]
"""


def rss_mb(pid: int) -> float:
    return fp._status_values(Path(f"/proc/{pid}/status"), ("VmRSS",)).get("VmRSS", 0) / 1024


def server_pid(bringup: fp.Started, timeout: float = 30.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for reading in bringup.read().values():
            if reading.name == "measurement_server":
                return reading.pid
        time.sleep(0.2)
    raise RuntimeError("no measurement_server process under dc-bringup")


def one_run(workdir: Path, run: int, domain: int, args: argparse.Namespace) -> dict[str, Any]:
    home = workdir / f"run{run}"
    home.mkdir()
    env = fp.environment(home, domain)
    domain = fp.quiet_domain(domain, env)
    env["ROS_DOMAIN_ID"] = str(domain)
    params = home / "recorder_memory.yaml"
    params.write_text(PARAMS.format(pre=args.pre, post=args.post, mb=args.mb))
    records = home / "var/dc/records/incidents.jsonl"
    samples: list[tuple[float, float, float]] = []  # (s since "DC is up", wall clock s, RSS MiB)
    marks: dict[str, float] = {}
    with contextlib.ExitStack() as stack:
        bringup = stack.enter_context(
            fp.started([fp.venv_script("dc-bringup"), str(params)], env, home, home / "dc-bringup.log", 60.0)
        )
        fp.wait_for_up(bringup, 120.0)
        pid = server_pid(bringup)
        t0 = time.monotonic()

        def sample_for(seconds: float, until: Any = lambda: False) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end and not until():
                samples.append((round(time.monotonic() - t0, 2), time.time(), round(rss_mb(pid), 1)))
                time.sleep(args.every)

        sample_for(3.0)  # before any topic
        marks["publisher"] = time.monotonic() - t0
        publisher = [sys.executable, "-c", PUBLISHER, str(args.fps)]
        stack.enter_context(fp.started(publisher, env, home, home / "publisher.log", 10.0))
        sample_for(args.idle)
        marks["trigger"] = time.monotonic() - t0
        trigger = subprocess.run(
            [fp.venv_script("dc"), "trigger", "incidents", "--reason", "benchmark"],
            env=env,
            cwd=home,
            capture_output=True,
            text=True,
            timeout=60,
        )
        if trigger.returncode:
            raise RuntimeError(f"dc trigger failed: {trigger.stdout}{trigger.stderr}")
        sample_for(120.0, lambda: records.exists() and records.stat().st_size > 0)
        record_seen = time.time()
        sample_for(args.after)
        if bringup.process.poll() is not None:
            raise RuntimeError(f"dc-bringup exited:\n{fp._tail(bringup.log)}")
    lines = records.read_text().splitlines() if records.exists() else []
    record = json.loads(lines[0]) if lines else {}

    # The phases by the wall clock: the trigger's and the window's end as the record gives them, the file
    # written by the time its record reached the file destination.
    opened, closed = record["triggers"][0]["time"], record["end"]

    def peak(start: float, end: float) -> float:
        return max((rss for _, wall, rss in samples if start <= wall < end), default=0.0)

    before = [rss for t, _, rss in samples if t < marks["publisher"]]
    idle_full = [rss for t, _, rss in samples if marks["trigger"] - 10 <= t < marks["trigger"]]
    return {
        "run": run,
        "domain": domain,
        "loadavg": os.getloadavg(),
        "marks_s": marks,
        "rss_before_topics_mb": statistics.median(before) if before else None,
        "rss_idle_ring_full_mb": statistics.median(idle_full) if idle_full else None,
        "rss_peak_idle_mb": max(rss for t, _, rss in samples if marks["publisher"] <= t < marks["trigger"]),
        "rss_peak_window_open_mb": peak(opened, closed),
        "rss_peak_writing_mb": peak(closed, record_seen),
        "rss_after_mb": samples[-1][2] if samples else None,
        "record": {
            k: record.get(k) for k in ("start", "end", "messages", "size", "cut_by_memory_bound", "topics", "triggers")
        },
        "samples": samples,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mb", type=float, default=200.0, help="the Recorder's max_memory_mb")
    parser.add_argument("--pre", type=float, default=10.0, help="pre_trigger (s)")
    parser.add_argument("--post", type=float, default=5.0, help="post_trigger (s)")
    parser.add_argument("--fps", type=float, default=30.0, help="the raw camera's rate")
    parser.add_argument("--idle", type=float, default=30.0, help="seconds of topics before the trigger")
    parser.add_argument("--after", type=float, default=15.0, help="seconds sampled after the record is written")
    parser.add_argument("--every", type=float, default=0.25, help="seconds between two RSS readings")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--domain", type=int, default=random.randint(100, 180), help="first ROS_DOMAIN_ID")
    parser.add_argument("--json", type=Path, help="benchmarks/results/recorder_memory_<date>.json")
    args = parser.parse_args()
    started_at = datetime.now(UTC)
    runs = []
    domain = args.domain
    with tempfile.TemporaryDirectory(prefix="dc-bench-recorder-memory-") as tmp:
        for run in range(1, args.runs + 1):
            result = one_run(Path(tmp), run, domain, args)
            domain = result["domain"] + 1
            runs.append(result)
            r, record = result, result["record"]
            topics = {
                t["topic"]: (t["messages"], t["lost_to_memory_bound"], t.get("lost_in_transport"))
                for t in record["topics"] or []
            }
            print(
                f"run {run} (load {r['loadavg'][0]:.1f}): max_memory_mb {args.mb:g}; RSS (MB) before the topics "
                f"{r['rss_before_topics_mb']:.0f}, idle with the ring full {r['rss_idle_ring_full_mb']:.0f} "
                f"(peak {r['rss_peak_idle_mb']:.0f}), window open peak {r['rss_peak_window_open_mb']:.0f}, "
                f"writing peak {r['rss_peak_writing_mb']:.0f}, after {r['rss_after_mb']:.0f}; record: "
                f"cut_by_memory_bound={record['cut_by_memory_bound']}, window {record['end'] - record['start']:.1f} s, "
                f"(messages, lost_to_memory_bound, lost_in_transport) per topic {topics}",
                flush=True,
            )
    document = {
        "date": started_at.isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()},
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "runs": runs,
    }
    path = args.json or fp.REPO / "benchmarks" / "results" / f"recorder_memory_{started_at:%Y-%m-%d}.json"
    path.write_text(json.dumps(document, indent=1) + "\n")
    print(f"JSON: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
