"""A day on a small disk, simulated (issue 27 item 5): what a 50 MB budget keeps of 8 hours of a robot.

    .venv/bin/python benchmarks/small_disk_day.py [--hours 8] [--rate 8] [--budget 50M] [--link 0.1]

`dc sim --clock` drives DC's robot job (cmd_vel, position, speed, distance traveled, the map every 30
s, grouped into one "robot" record), the QR camera (an inspected image per shelf) and an incident
recorder (8 s of /odom and /tf, MCAP, triggered with `dc trigger` every --incident-every simulated
seconds: the Recorder's windows are in wall-clock time, so at a high rate the robot's stops would
extend one incident for ever) at --rate simulated seconds per wall-clock
second, through dc-bringup with --use-sim-time. destination_server keeps everything within
flb.disk_budget (records and saved files), and uploads the files to a local S3 store (SeaweedFS) over
a MinIO destination capped at --link of what the robot produces (measured first, in a calibration
run of --calibrate simulated seconds without a cap); the records go to a JSON-lines file.

Retention priorities: incidents 10, map 5, front_camera 0; the first and last 2 files of each run are
evicted last. Every 2 s the metrics are read: the most the budget ever held (saved files + records
waiting, summed from two readings) is reported against the budget, with DC's own account
(``disk_budget`` in the metrics: the most it held after a check, and how many checks left it over).
At the end, per measurement: files produced, sent
(delivered and verified), kept on disk, evicted (and of those, never sent), with their bytes; and
whether anything was evicted unsent while a lower priority still had a file it could give. The last
metrics document is written to ``metrics.json`` in the run's work folder.

Above a rate of ~16 the camera misses the robot's stops (3 simulated seconds, shorter than the
gap between two frames): 8 is the highest rate at which a day's images are all there (1 hour of
wall-clock time for 8 simulated hours).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from dc_bringup.local_servers.processes import free_port
from dc_bringup.local_servers.seaweedfs import SeaweedS3Server
from dc_destinations.settings import parse_size

BIN = Path(sys.executable).parent
PRIORITIES = {"incidents": 10, "map": 5, "front_camera": 0}
# The retention_priority of each destination's queue of records (params below).
QUEUE_PRIORITIES = {"records": 5, "minio": 0}
KEEP_RUN_ENDS = 2


def params(work: Path, s3: SeaweedS3Server, port: int, budget: str, cap: str) -> str:
    s = s3.settings()
    capped = f'      max_bytes_per_s: "{cap}"\n' if cap else ""
    return f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["cmd_vel", "position", "speed", "distance_traveled", "map", "front_camera", "incidents"]
    condition_plugins: ["moving", "inspected_exists"]
    custom_str_params_list: ["robot_name"]
    custom_str_params:
      robot_name: {{name: robot_name, value: C3PO}}
    run_id: {{enabled: true, counter: true, counter_path: "{work}/run_id"}}
    save_local_base_path: "{work}/data/"
    all_base_path: "=robot_name/%Y/%m/%d/%H"
    moving: {{plugin: "dc_conditions/Moving", odom_topic: "/odom", speed_threshold: 0.05}}
    inspected_exists: {{plugin: "dc_conditions/Exist", key: "inspected"}}
    cmd_vel: {{plugin: "dc_measurements/CmdVel", group_key: "cmd_vel", topic_output: "/dc/measurement/cmd_vel"}}
    position:
      plugin: "dc_measurements/Position"
      group_key: "position"
      topic_output: "/dc/measurement/position"
      global_frame: "odom"
      robot_base_frame: "base_link"
    speed: {{plugin: "dc_measurements/Speed", group_key: "speed", odom_topic: "/odom",
             topic_output: "/dc/measurement/speed"}}
    distance_traveled:
      plugin: "dc_measurements/DistanceTraveled"
      global_frame: "odom"
      robot_base_frame: "base_link"
      polling_interval: 10000
      tags: ["records"]
    map:
      plugin: "dc_measurements/Map"
      polling_interval: 30000
      save_path: "map/%Y-%m-%dT%H-%M-%S"
      save_map_timeout: 4.0
      remote_prefixes: [""]
      remote_keys: ["minio"]
      tags: ["records", "minio"]
    front_camera:
      plugin: "dc_measurements/Camera"
      if_none_conditions: ["moving"]
      if_all_conditions: ["inspected_exists"]
      polling_interval: 500
      init_collect: false
      condition_max_measurements: 1
      cam_topic: "/camera/image_raw"
      cam_name: front_camera
      draw_det_barcodes: true
      save_raw_img: false
      save_rotated_img: false
      save_detections_img: true
      save_inspected_path: "front_camera/inspected/%Y-%m-%dT%H-%M-%S"
      detection_modules: ["barcode"]
      remote_prefixes: [""]
      remote_keys: ["minio"]
      tags: ["records", "minio"]
    incidents:
      plugin: "dc_measurements/Recorder"
      polling_interval: 100
      topics: ["/odom", "/tf", "/tf_static"]
      pre_trigger: 5.0
      post_trigger: 3.0
      max_memory_mb: 64.0
      cooldown: 2.0
      # Counted in wall-clock hours: the default 60 would stop a day's incidents after the first 60.
      max_incidents_per_hour: 10000
      compression: "zstd"
      save_path: "incidents/%Y-%m-%dT%H-%M-%S"
      remote_prefixes: [""]
      remote_keys: ["minio"]
      tags: ["records", "minio"]
group_server:
  ros__parameters:
    groups: ["robot"]
    robot:
      inputs: ["/dc/measurement/cmd_vel", "/dc/measurement/position", "/dc/measurement/speed"]
      output: "/dc/group/robot"
      sync_delay: 5.0
      group_key: "robot"
      tags: ["records"]
destination_server:
  ros__parameters:
    flb:
      flush: 1
      storage_path: "{work}/buffer"
      http_port: {port}
      disk_budget: "{budget}"
      retention_priorities: {json.dumps(PRIORITIES)}
      keep_run_ends: {KEEP_RUN_ENDS}
    destination_plugins: ["records", "minio"]
    records:
      plugin: "dc_destinations/File"
      inputs: ["/dc/group/robot", "/dc/measurement/distance_traveled", "/dc/measurement/map",
               "/dc/measurement/front_camera", "/dc/measurement/incidents"]
      path: "{work}/records"
      file: "records.jsonl"
      retention_priority: {QUEUE_PRIORITIES["records"]}
    minio:
      plugin: "dc_destinations/MinIO"
      inputs: ["/dc/measurement/map", "/dc/measurement/front_camera", "/dc/measurement/incidents"]
      endpoint: "127.0.0.1:{s3.port}"
      use_ssl: false
      access_key_id: "{s["aws_access_key_id"]}"
      secret_access_key: "${{DC_BENCH_S3_SECRET}}"
      bucket: "{s3.bucket}"
      allowed_roots: ["{work}/data"]
      src_fields: ["local_paths.pgm", "local_paths.yaml", "local_paths.inspected", "local_paths.mcap"]
      upload_fields: ["remote_paths.minio.pgm", "remote_paths.minio.yaml", "remote_paths.minio.inspected",
                      "remote_paths.minio.mcap"]
      part_size: "5M"
      # A batch is confirmed whole: under a cap of ~1 kB/s, 500 images would take hours before any counts sent.
      batch_size: 5
      retention_priority: {QUEUE_PRIORITIES["minio"]}
{capped}"""


def metrics(port: int) -> dict[str, Any] | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/v1/metrics", timeout=3) as response:
            document: dict[str, Any] = json.loads(response.read())
            return document
    except (OSError, ValueError):
        return None


def run(
    work: Path, s3: SeaweedS3Server, sim_s: float, rate: float, budget: str, cap: str, every: float
) -> dict[str, Any]:
    """One run of ``sim_s`` simulated seconds; the last metrics, with the most the budget held."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    port = free_port()
    (work / "params.yaml").write_text(params(work, s3, port, budget, cap))
    env = {**os.environ, "DC_BENCH_S3_SECRET": str(s3.settings()["aws_secret_access_key"])}
    logs = (work / "sim.log").open("w"), (work / "bringup.log").open("w")
    bringup = subprocess.Popen(
        [str(BIN / "dc-bringup"), str(work / "params.yaml"), "--use-sim-time"],
        stdout=logs[1],
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,
    )
    sim = None
    most = 0
    last: dict[str, Any] | None = None
    try:
        deadline = time.monotonic() + 60
        while metrics(port) is None:
            if time.monotonic() > deadline or bringup.poll() is not None:
                raise SystemExit(f"destination_server did not answer; see {work / 'bringup.log'}")
            time.sleep(0.5)
        sim = subprocess.Popen(
            [str(BIN / "dc"), "sim", "--clock", "--loop", "--rate", str(rate), "--duration", str(sim_s)],
            stdout=logs[0],
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        triggered = time.monotonic()
        while sim.poll() is None:
            time.sleep(2)
            if time.monotonic() - triggered >= every / rate:
                triggered = time.monotonic()
                subprocess.run(
                    [str(BIN / "dc"), "trigger", "incidents", "--reason", "benchmark"],
                    capture_output=True,
                    timeout=30,
                    check=False,
                )
            document = metrics(port)
            if document is None:
                continue
            last = document
            held = sum(d.get("buffered_bytes") or 0 for d in document["destinations"].values())
            most = max(most, held + int(document.get("saved_files", {}).get("bytes", 0)))
        time.sleep(5)  # the last records and files reach destination_server
        last = metrics(port) or last
    finally:
        for process in (sim, bringup):
            if process is not None and process.poll() is None:
                os.killpg(process.pid, signal.SIGINT)
                try:
                    process.wait(30)
                except subprocess.TimeoutExpired:
                    os.killpg(process.pid, signal.SIGKILL)
        for log in logs:
            log.close()
    if last is None:
        raise SystemExit(f"no metrics were read; see {work}")
    last["most_held"] = most
    (work / "metrics.json").write_text(json.dumps(last, indent=1))
    return last


def produced_bytes(document: dict[str, Any]) -> int:
    files = sum(m["produced_bytes"] for m in document.get("saved_files", {}).get("measurements", {}).values())
    return int(files + (document["destinations"]["records"].get("buffered_bytes") or 0))


def table(document: dict[str, Any], budget: int) -> str:
    measurements = document.get("saved_files", {}).get("measurements", {})
    lines = [
        "| measurement | retention priority | produced | sent (verified) | kept | evicted | of them never sent "
        "| dead-lettered |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, m in sorted(measurements.items(), key=lambda item: -item[1]["retention_priority"]):
        lines.append(
            f"| {name} | {m['retention_priority']} | {m['produced']} ({m['produced_bytes'] / 1e6:.1f} MB) | "
            f"{m['delivered']} | {m['kept']} ({m['kept_bytes'] / 1e6:.1f} MB) | "
            f"{m['evicted']} ({m['evicted_bytes'] / 1e6:.1f} MB) | {m['evicted_unsent']} | |"
        )
    for name, d in sorted(document["destinations"].items()):
        lines.append(
            f"| records of {name} | {QUEUE_PRIORITIES.get(name, '')} | {d['received']} | {d['sent']} | "
            f"{d['buffered']} | {d['evicted']} | {d['evicted']} | {d['dead_lettered']} |"
        )
    lines.append(f"\nmost held at once: {document['most_held'] / 1e6:.1f} MB of a {budget / 1e6:.1f} MB budget")
    account = document.get("disk_budget")
    if account:  # DC's own account after each check (an admission, the tick): one reading, not two summed
        lines.append(
            f"DC's account: most held {account['most_held']:,} of {account['budget']:,} bytes; "
            f"checks that left it over: {account['checks_left_over']}"
        )
    # An unsent file evicted of a priority while a lower one kept more than its run ends would break the rule.
    broken = [
        (high, low)
        for high, h in measurements.items()
        for low, lo in measurements.items()
        if h["retention_priority"] > lo["retention_priority"]
        and h["evicted_unsent"]
        and lo["kept"] > lo["delivered"] + 2 * KEEP_RUN_ENDS
    ]
    lines.append("priority rule: " + ("held" if not broken else f"BROKEN: {broken}"))
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--hours", type=float, default=8.0, help="simulated hours")
    parser.add_argument("--rate", type=float, default=8.0, help="simulated seconds per wall-clock second")
    parser.add_argument("--budget", default="50M", help="flb.disk_budget")
    parser.add_argument("--link", type=float, default=0.1, help="upload cap as a fraction of what is produced")
    parser.add_argument("--calibrate", type=float, default=300.0, help="simulated seconds of the calibration run")
    parser.add_argument("--incident-every", type=float, default=160.0, help="simulated seconds between incidents")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="dc-small-disk-"))
    with SeaweedS3Server(root / "s3") as s3:
        calibration = run(root / "calibrate", s3, args.calibrate, args.rate, "10G", "", args.incident_every)
        per_sim_s = produced_bytes(calibration) / args.calibrate
        cap = max(int(per_sim_s * args.rate * args.link), 1024)
        print(
            f"calibration: {per_sim_s / 1e3:.1f} kB per simulated second; upload cap {cap / 1e3:.1f} kB/s "
            f"of wall-clock time at rate {args.rate:g} ({args.link:.0%})"
        )
        day = run(root / "day", s3, args.hours * 3600, args.rate, args.budget, str(cap), args.incident_every)
    print(table(day, parse_size(args.budget) or 0))
    print(f"work folder (logs, params): {root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
