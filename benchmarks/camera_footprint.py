"""What a Camera measurement costs measurement_server: a 30 fps 640x480 camera polled every second.

The Camera's subscription keeps only the newest frame and a poll converts, reads and saves at most
one (dc_measurements/camera/README.md): frames that arrive between polls should cost what any
subscriber pays to receive them, and nothing more. This script checks that claim in real
processes, each run in a ROS domain of its own (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST):

1. ``baseline``: a bare rclpy subscriber of the same topic and QoS (best effort, depth 1) taken by
   DC's intake loop — the receive path measurement_server uses — counting the frames, nothing else;
2. ``camera 1 s``: ``python -m dc_measurements.server PARAMS --autostart`` with one Camera
   (``detection_modules: ["barcode"]``, ``save_detections_img: true``, polling_interval 1000);
3. ``camera 1 s, no detection``: ``detection_modules: []``, ``save_raw_img: true`` (conversion
   and JPEG only, a record and a file at every poll);
4. ``camera 100 ms``: as 2 with polling_interval 100: ten times the polls for the same frames.

A publisher process sends ``sensor_msgs/Image`` bgr8 frames at --fps (paced on the wall clock),
a shelf label with a QR code and a Code 128 code (dc_sim.camera) for --switch seconds, then the
bare shelf for as long, so that half the polls read codes and publish a record and half do not.
Each receiver's CPU (utime+stime of /proc/<pid>/stat) is taken over --seconds after a warm-up;
frames, polls and records over the same window (the Camera's counters, served over HTTP with
``http_server: true``; the baseline prints its count); RSS and PSS (/proc/<pid>/smaps_rollup) at
the window's end. The poll's work alone (conversion, detection, drawing, JPEG, file) is timed in
this process on the same frames, so that the extra CPU of each camera run over the baseline can be
compared with what its polls should cost.

    .venv/bin/python benchmarks/camera_footprint.py [--seconds 30] [--fps 30] [--runs 1] [--json OUT]

Children are stopped with SIGTERM, then SIGKILL after 10 s (end_to_end.Child); every wait is
bounded; the temporary folder (logs, parameters, saved images) is deleted at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import re
import signal
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

# The repository's root: benchmarks/ is a namespace package there, which mypy resolves as well.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import end_to_end as e2e  # a sibling script

TOPIC = "/bench/camera/image_raw"
WIDTH, HEIGHT = 640, 480
MEASUREMENT = "camera"
# Discovery, the server's wait for a subscriber of its output (2 s at most) and the first polls
# (detector and JPEG encoder warming up) all fall before the window.
WARMUP_S = 6.0
PUBLISH_MARGIN_S = 2.0  # the publisher goes on this long after the window, so that it ends under load
POLL_COST_REPEATS = 30
HTTP_LINE = re.compile(r"metrics HTTP server on http://([0-9.]+):(\d+)/api/v1/")
# Fast DDS's default shared-memory segment (512 kB) cannot hold a 921,600-byte frame: frames then go
# over UDP in 64 kB fragments, and a best-effort reader loses most of them once the socket's receive
# buffer (net.core.rmem_default, 208 kB here) overflows. A robot streaming raw images gives Fast DDS
# a larger segment; so does this benchmark unless --transport default.
FASTDDS_PROFILE = Path(__file__).resolve().parent.parent / "params" / "fastdds" / "large_frames.xml"


@dataclass(frozen=True)
class Scenario:
    name: str
    polling_ms: int  # 0: the bare subscriber
    detection: bool = True


SCENARIOS = (
    Scenario("baseline", 0),
    Scenario("camera 1 s", 1000),
    Scenario("camera 1 s, no detection", 1000, detection=False),
    Scenario("camera 100 ms", 100),
)


# ---------------------------------------------------------------------------------------------
# child roles
# ---------------------------------------------------------------------------------------------


def _image_messages() -> tuple[Any, Any]:
    """The label frame and the bare shelf frame as bgr8 ``sensor_msgs/Image`` messages."""
    from sensor_msgs.msg import Image

    from dc_sim.camera import CameraView, ShelfLabel, label_frame

    frames = (
        label_frame(ShelfLabel("WH1/AISLE-1/SHELF-01", "PAL-1000", "Code128"), WIDTH, HEIGHT),
        CameraView([], WIDTH, HEIGHT).frame(None),  # no label in view: the bare shelf
    )
    messages = []
    for frame in frames:
        msg = Image()
        msg.header.frame_id = "bench_camera"
        msg.height, msg.width = frame.shape[:2]
        msg.encoding = "bgr8"
        msg.step = frame.shape[1] * 3
        msg.data = frame.tobytes()
        messages.append(msg)
    return messages[0], messages[1]


def role_publisher(fps: float, seconds: float, switch_s: float) -> None:
    """Wait for a subscriber, print ready, wait for 'go', publish for ``seconds``, print what was sent."""
    import rclpy
    from sensor_msgs.msg import Image

    from dc_measurements.camera import FRAME_QOS

    rclpy.init()
    node = rclpy.create_node(f"bench_camera_{os.getpid()}")
    publisher = node.create_publisher(Image, TOPIC, FRAME_QOS)
    label, bare = _image_messages()
    deadline = time.monotonic() + e2e.START_DEADLINE_S
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    if publisher.get_subscription_count() < 1:
        print("nomatch", flush=True)
        return
    time.sleep(0.5)  # let discovery finish on the subscriber's side too
    print("ready", flush=True)
    sys.stdin.readline()
    stop = threading.Event()

    def watch_stdin() -> None:  # EOF: the parent is done (or gone), stop publishing
        sys.stdin.read()
        stop.set()

    threading.Thread(target=watch_stdin, daemon=True).start()
    clock = node.get_clock()
    sent = {"label": 0, "bare": 0, "late": 0}
    period = 1.0 / fps
    start = time.perf_counter()
    due = start
    while not stop.is_set() and due - start < seconds:
        delay = due - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        elif delay < -period:
            # Behind by more than a frame (the machine was busy): skip the slots rather than burst.
            sent["late"] += 1
            due = time.perf_counter()
        with_label = int((due - start) / switch_s) % 2 == 0
        msg = label if with_label else bare
        msg.header.stamp = clock.now().to_msg()
        publisher.publish(msg)
        sent["label" if with_label else "bare"] += 1
        due += period
    print(json.dumps({"sent": sent["label"] + sent["bare"], **sent}), flush=True)
    stop.wait(30.0)  # the parent closes stdin when it is done
    node.destroy_node()
    rclpy.shutdown()


def role_subscriber() -> None:
    """The cheapest receiver: the Camera's topic and QoS, taken by DC's intake loop, frames counted."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image

    from dc_core.intake import Intake
    from dc_core.lifecycle import ServerLoop
    from dc_measurements.camera import FRAME_QOS

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    node = rclpy.create_node(f"bench_frames_{os.getpid()}")
    count = [0]

    def on_frame(msg: Any, info: Any) -> None:
        count[0] += 1

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    intake = Intake(node)
    intake.subscribe(Image, TOPIC, on_frame, FRAME_QOS)
    reported = [-1]

    def report() -> None:  # a line every 0.1 s at most: negligible beside 30 frames of 900 kB a second
        if count[0] != reported[0]:
            reported[0] = count[0]
            print(f"frames {count[0]}", flush=True)

    node.create_timer(0.1, report)
    print("ready", flush=True)
    ServerLoop(executor, intake).run(stop, e2e._StderrLog())
    report()
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()


# ---------------------------------------------------------------------------------------------
# measurements
# ---------------------------------------------------------------------------------------------


@dataclass
class Result:
    """One receiver over one window."""

    scenario: str
    run: int
    window_s: float
    cpu_s: float
    frames: int  # received by the measured process in the window
    polls: int  # polls that ran (a frame read or not)
    read: int  # polls that found a new frame and converted it
    records: int
    images: int  # files written
    rss_mb: float
    pss_mb: float
    hwm_mb: float
    sent: int  # frames the publisher sent over its whole run
    late: int  # frame slots the publisher missed
    minor_faults: int = 0  # pages first touched in the window: fresh buffers for frames cost these

    @property
    def cpu_percent(self) -> float:
        return self.cpu_s / self.window_s * 100

    @property
    def ms_per_frame(self) -> float:
        return self.cpu_s / max(self.frames, 1) * 1e3

    @property
    def ms_per_record(self) -> float | None:
        return self.cpu_s / self.records * 1e3 if self.records else None


def minor_faults(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[7])  # minflt (field 10)


def memory(pid: int) -> tuple[float, float, float]:
    """RSS, PSS and peak RSS in MB."""
    status = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            status[key] = int(rest.split()[0]) / 1024
    pss = 0.0
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
        if line.startswith("Pss:"):
            pss = int(line.split()[1]) / 1024
    return status["VmRSS"], pss, status["VmHWM"]


def server_params(folder: Path, scenario: Scenario) -> Path:
    params = folder / "measurement_server.yaml"
    modules = '["barcode"]' if scenario.detection else "[]"
    params.write_text(
        f"""measurement_server:
  ros__parameters:
    measurement_plugins: ["{MEASUREMENT}"]
    run_id:
      enabled: false
    save_local_base_path: "{folder / "data"}"
    http_server: true
    http_port: 0
    {MEASUREMENT}:
      plugin: "dc_measurements/Camera"
      polling_interval: {scenario.polling_ms}
      cam_topic: "{TOPIC}"
      cam_name: "bench_camera"
      detection_modules: {modules}
      save_detections_img: true
      save_raw_img: {"false" if scenario.detection else "true"}
"""
    )
    return params


def camera_counters(port: int) -> dict[str, int]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/v1/metrics", timeout=5.0) as response:
        document = json.loads(response.read())
    counters: dict[str, int] = document["measurements"][MEASUREMENT]
    return counters


def measure(workdir: Path, domain: int, scenario: Scenario, run: int, args: argparse.Namespace) -> Result:
    folder = workdir / f"run{run}-{scenario.name.replace(' ', '_').replace(',', '')}"
    folder.mkdir()
    bench = e2e.Bench(folder, domain)
    bench.env["HOME"] = str(folder)
    if args.transport == "shm":
        bench.env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
    me = [sys.executable, str(Path(__file__).resolve())]
    if scenario.polling_ms == 0:
        receiver = e2e.Child([*me, "--role", "subscriber"], bench.env, folder / "subscriber.log")
    else:
        argv = [sys.executable, "-m", "dc_measurements.server", str(server_params(folder, scenario)), "--autostart"]
        receiver = e2e.Child(argv, bench.env, folder / "measurement_server.log")
    with e2e.running(receiver):
        counters: Callable[[], dict[str, int]]
        if scenario.polling_ms == 0:
            if receiver.wait_line(lambda line: line == "ready", e2e.START_DEADLINE_S) is None:
                raise RuntimeError(f"the subscriber did not start; see {receiver.log.name}")

            def counters() -> dict[str, int]:
                counts = [int(line.split()[1]) for line in receiver.lines if line.startswith("frames ")]
                return {"frames": counts[-1] if counts else 0}

        else:
            found: list[re.Match[str]] = []

            def started() -> bool:
                found[:] = [m for m in [HTTP_LINE.search(receiver.log_text())] if m]
                return bool(found) or receiver.process.poll() is not None

            if not e2e.wait_until(started, e2e.START_DEADLINE_S) or not found:
                raise RuntimeError(f"measurement_server did not start; see {receiver.log.name}")
            port = int(found[0].group(2))

            def counters() -> dict[str, int]:
                return camera_counters(port)

        publish_s = WARMUP_S + args.seconds + PUBLISH_MARGIN_S
        publisher = e2e.Child(
            [
                *me,
                "--role",
                "publisher",
                "--fps",
                str(args.fps),
                "--switch",
                str(args.switch),
                "--publish-seconds",
                str(publish_s),
            ],
            bench.env,
            folder / "publisher.log",
            stdin=True,
        )
        with e2e.running(publisher):
            if publisher.wait_line(lambda line: line in ("ready", "nomatch"), e2e.START_DEADLINE_S) != "ready":
                raise RuntimeError(f"the publisher found no subscriber; see {publisher.log.name}")
            publisher.send("go\n")
            time.sleep(WARMUP_S)
            c0, cpu0, t0 = counters(), e2e.cpu_seconds(receiver.pid), time.monotonic()
            faults0 = minor_faults(receiver.pid)
            time.sleep(args.seconds)
            c1, cpu1, t1 = counters(), e2e.cpu_seconds(receiver.pid), time.monotonic()
            faults1 = minor_faults(receiver.pid)
            rss, pss, hwm = memory(receiver.pid)
            report = publisher.wait_line(lambda line: line.startswith("{"), PUBLISH_MARGIN_S + 30.0)
            if report is None:
                raise RuntimeError(f"the publisher did not finish; see {publisher.log.name}")
            sent = json.loads(report)
        if receiver.process.poll() is not None:
            raise RuntimeError(f"{scenario.name}: the receiver exited; see {receiver.log.name}")

    def delta(key: str) -> int:
        return int(c1.get(key, 0)) - int(c0.get(key, 0))

    polls = delta("collected") + delta("empty") + delta("errors")
    result = Result(
        scenario=scenario.name,
        run=run,
        window_s=t1 - t0,
        cpu_s=cpu1 - cpu0,
        frames=delta("frames"),
        polls=polls,
        read=polls - delta("stale"),
        records=delta("published"),
        images=delta("saved_images"),
        rss_mb=rss,
        pss_mb=pss,
        hwm_mb=hwm,
        sent=int(sent["sent"]),
        late=int(sent["late"]),
        minor_faults=faults1 - faults0,
    )
    return result


# ---------------------------------------------------------------------------------------------
# the poll's work alone, in this process
# ---------------------------------------------------------------------------------------------


def _cpu_ms(work: Callable[[], object], repeats: int) -> float:
    """Median CPU ms of ``work`` (all threads of this process), after two warm-up calls."""
    work()
    work()
    times = []
    for _ in range(repeats):
        started = time.process_time()
        work()
        times.append((time.process_time() - started) * 1e3)
    return statistics.median(times)


def poll_costs(folder: Path, repeats: int) -> dict[str, float]:
    """CPU ms of each step of a poll on the benchmark's frames, as dc_measurements.camera does them."""
    from dc_measurements.camera.detection import BarcodeDetector, draw_detections
    from dc_measurements.camera.images import encode_jpeg, image_to_array

    label_msg, bare_msg = _image_messages()
    label, bare = image_to_array(label_msg), image_to_array(bare_msg)
    detector = BarcodeDetector(["barcode"])
    detections = detector.detect(label)
    if len(detections) < 2 or detector.detect(bare):
        raise RuntimeError(f"the label frame should give 2 codes and the bare one none: {detections}")
    drawn = draw_detections(label, detections)
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / "image.jpg"
    content = encode_jpeg(drawn, 90)

    def write() -> None:  # as PendingFiles does: a temporary name, then renamed into place
        part = folder / "image.jpg.part"
        part.write_bytes(content)
        part.replace(target)

    costs = {
        "convert": _cpu_ms(lambda: image_to_array(label_msg), repeats),
        "detect_label": _cpu_ms(lambda: detector.detect(label), repeats),
        "detect_bare": _cpu_ms(lambda: detector.detect(bare), repeats),
        "draw": _cpu_ms(lambda: draw_detections(label, detections), repeats),
        "jpeg_inspected": _cpu_ms(lambda: encode_jpeg(drawn, 90), repeats),
        "jpeg_raw_label": _cpu_ms(lambda: encode_jpeg(label, 90), repeats),
        "jpeg_raw_bare": _cpu_ms(lambda: encode_jpeg(bare, 90), repeats),
        "write": _cpu_ms(write, repeats),
    }
    c = costs
    costs["poll_label"] = c["convert"] + c["detect_label"] + c["draw"] + c["jpeg_inspected"] + c["write"]
    costs["poll_bare"] = c["convert"] + c["detect_bare"]
    costs["poll_no_detection"] = c["convert"] + (c["jpeg_raw_label"] + c["jpeg_raw_bare"]) / 2 + c["write"]
    return costs


def predicted_poll_ms(result: Result, costs: dict[str, float]) -> float:
    """CPU ms the window's polls should cost, from the steps timed in this process."""
    if "no detection" in result.scenario:
        return result.read * costs["poll_no_detection"]
    # With detection a poll publishes a record exactly when it reads codes: a label frame.
    return result.records * costs["poll_label"] + (result.read - result.records) * costs["poll_bare"]


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------


def _median(values: list[float]) -> float:
    return statistics.median(values)


def summarise(results: list[Result], costs: dict[str, float]) -> dict[str, dict[str, float]]:
    """Per scenario, the median of each figure over the runs; extra CPU over the same run's baseline."""
    baseline = {r.run: r for r in results if r.scenario == "baseline"}
    summary: dict[str, dict[str, float]] = {}
    for scenario in SCENARIOS:
        rows = [r for r in results if r.scenario == scenario.name]
        if not rows:
            continue
        figures: dict[str, list[float]] = {}
        for r in rows:
            base = baseline[r.run]
            values = {
                "cpu_percent": r.cpu_percent,
                "ms_per_frame": r.ms_per_frame,
                "frames_per_s": r.frames / r.window_s,
                "minor_faults_per_frame": r.minor_faults / max(r.frames, 1),
                "polls_per_s": r.polls / r.window_s,
                "read_per_s": r.read / r.window_s,
                "records_per_s": r.records / r.window_s,
                "rss_mb": r.rss_mb,
                "pss_mb": r.pss_mb,
                "ratio_to_baseline": r.cpu_percent / base.cpu_percent,
                # CPU ms per second above the bare subscriber of the same run, and what the polls should cost.
                "extra_ms_per_s": (r.cpu_percent - base.cpu_percent) * 10,
                "extra_ms_per_frame": r.ms_per_frame - base.ms_per_frame,
                "predicted_ms_per_s": predicted_poll_ms(r, costs) / r.window_s,
            }
            if r.ms_per_record is not None:
                values["ms_per_record"] = r.ms_per_record
            if r.read:
                values["extra_ms_per_read_poll"] = (
                    (r.cpu_s / r.window_s - base.cpu_s / base.window_s) * 1e3 / (r.read / r.window_s)
                )
            for key, value in values.items():
                figures.setdefault(key, []).append(value)
        summary[scenario.name] = {key: _median(values) for key, values in figures.items()}
    return summary


def print_report(summary: dict[str, dict[str, float]], costs: dict[str, float], args: argparse.Namespace) -> None:
    print(
        f"\nmedians of {args.runs} run(s), {args.fps:g} fps {WIDTH}x{HEIGHT} bgr8, window {args.seconds:g} s "
        f"after {WARMUP_S:g} s, label/bare every {args.switch:g} s"
    )
    header = (
        f"{'scenario':<26} {'CPU %':>6} {'x base':>7} {'frames/s':>8} {'ms/frame':>8} {'polls/s':>7} "
        f"{'rec/s':>6} {'ms/record':>9} {'RSS MB':>7} {'PSS MB':>7} {'faults/frame':>12}"
    )
    print(header)
    for name, s in summary.items():
        record = f"{s['ms_per_record']:9.1f}" if "ms_per_record" in s else f"{'-':>9}"
        polls = f"{s['polls_per_s']:7.2f}" if name != "baseline" else f"{'-':>7}"
        print(
            f"{name:<26} {s['cpu_percent']:6.2f} {s['ratio_to_baseline']:6.2f}x {s['frames_per_s']:8.1f} "
            f"{s['ms_per_frame']:8.3f} {polls} {s['records_per_s']:6.2f} {record} {s['rss_mb']:7.1f} "
            f"{s['pss_mb']:7.1f} {s['minor_faults_per_frame']:12.0f}"
        )
    print("\nthe poll's steps timed in this process (CPU ms, median of", POLL_COST_REPEATS, "each):")
    print("  " + ", ".join(f"{key} {value:.2f}" for key, value in costs.items()))
    print(
        "\nclaim: frames that arrive between polls cost no decoding, i.e. camera CPU - baseline CPU = the polls' work"
    )
    for name, s in summary.items():
        if name == "baseline":
            continue
        measured, predicted = s["extra_ms_per_s"], s["predicted_ms_per_s"]
        print(
            f"  {name:<26} above baseline {measured:6.1f} ms CPU/s ({s['extra_ms_per_frame']:+.3f} ms/frame); "
            f"its {s['read_per_s']:.2f} polls/s with a frame should cost {predicted:5.1f} ms/s; "
            f"unexplained {measured - predicted:+6.1f} ms/s"
        )
    if "camera 1 s" in summary and "camera 100 ms" in summary:
        slow, fast = summary["camera 1 s"], summary["camera 100 ms"]
        polls_ratio = fast["read_per_s"] / slow["read_per_s"]
        # Against a baseline that costs more than the 1 s run, the ratio means nothing: said so.
        extra = slow["extra_ms_per_s"]
        extra_ratio = f"{fast['extra_ms_per_s'] / extra:.1f}x" if extra > 0 else "n/a (1 s run below baseline)"
        slope = (fast["extra_ms_per_s"] - slow["extra_ms_per_s"]) / (fast["read_per_s"] - slow["read_per_s"])
        intercept = slow["extra_ms_per_s"] - slope * slow["read_per_s"]
        mean_poll = (costs["poll_label"] + costs["poll_bare"]) / 2
        print(
            f"  100 ms / 1 s: {polls_ratio:.1f}x the polls, {extra_ratio} the CPU above baseline; "
            f"marginal cost {slope:.1f} ms per poll (timed here: {mean_poll:.1f} ms, half label, half bare); "
            f"left at zero polls {intercept:+.1f} ms/s"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--role", choices=["main", "publisher", "subscriber"], default="main")
    parser.add_argument("--publish-seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, default=30.0, help="measurement window of each run, after warm-up")
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second of the camera")
    parser.add_argument("--switch", type=float, default=3.0, help="seconds of label frames, then of bare frames")
    parser.add_argument("--runs", type=int, default=1, help="repeat every scenario; medians are reported")
    parser.add_argument(
        "--transport",
        choices=["shm", "default"],
        default="shm",
        help="shm: Fast DDS with a 16 MB shared-memory segment (frames fit); default: Fast DDS as shipped",
    )
    parser.add_argument("--no-fast", action="store_true", help="skip the camera polled every 100 ms")
    parser.add_argument(
        "--domain", type=int, default=random.randint(100, 200), help="first ROS_DOMAIN_ID (one per scenario)"
    )
    parser.add_argument("--json", default=str(e2e.REPO / "benchmarks" / "results" / "camera_footprint.json"))
    args = parser.parse_args()
    if args.role == "publisher":
        role_publisher(args.fps, args.publish_seconds, args.switch)
        return
    if args.role == "subscriber":
        role_subscriber()
        return

    scenarios = [s for s in SCENARIOS if not (args.no_fast and s.polling_ms == 100)]
    started = datetime.now(UTC)
    results: list[Result] = []
    with tempfile.TemporaryDirectory(prefix="dc-bench-camera-") as tmp:
        workdir = Path(tmp)
        costs = poll_costs(workdir / "poll", POLL_COST_REPEATS)
        for run in range(1, args.runs + 1):
            # Each run starts with another scenario: a drift of the machine does not favour one of them.
            shift = (run - 1) % len(scenarios)
            for scenario in scenarios[shift:] + scenarios[:shift]:
                # A domain per scenario: a child that outlived its run cannot feed the next one.
                result = measure(workdir, args.domain + scenarios.index(scenario), scenario, run, args)
                results.append(result)
                print(
                    f"run {run}: {scenario.name:<26} CPU {result.cpu_percent:5.2f} %  frames {result.frames:5d} "
                    f"polls {result.polls:4d} read {result.read:4d} records {result.records:4d} "
                    f"images {result.images:4d}  RSS {result.rss_mb:5.1f} MB PSS {result.pss_mb:5.1f} MB  "
                    f"faults/frame {result.minor_faults / max(result.frames, 1):5.0f}  "
                    f"(sent {result.sent}, late {result.late})",
                    flush=True,
                )
    summary = summarise(results, costs)
    print_report(summary, costs, args)
    document = {
        "date": started.isoformat(timespec="seconds"),
        "machine": {
            "cpus": os.cpu_count(),
            "processor": e2e._processor(),
            "python": platform.python_version(),
            "kernel": platform.release(),
        },
        "settings": {k: v for k, v in vars(args).items() if k not in ("role", "publish_seconds")},
        "warmup_s": WARMUP_S,
        "poll_costs_ms": costs,
        "results": [{**asdict(r), "cpu_percent": r.cpu_percent, "ms_per_frame": r.ms_per_frame} for r in results],
        "medians": summary,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nJSON: {args.json}")


if __name__ == "__main__":
    main()
