"""What DC costs on the robot at rest: CPU, memory and wake-ups of every process dc-bringup runs.

For each parameter file (--params, repeatable) and each mode (--mode NAME with its own
--bringup-args, so that two ways of starting DC are measured in one run and compared), the script
starts ``dc-bringup PARAMS`` as a user would, in a temporary folder that is both its HOME and its
working directory (buffers, records and ROS logs stay out of the repository), with a ROS domain of
its own (one where a probe finds no node) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, stdout
(the Stdout destination) to /dev/null. Once dc-bringup logs "DC is up" and --settle seconds have
passed, it reads /proc for dc-bringup and all its descendants at the start and end of a --window:

* CPU: utime+stime of /proc/<pid>/stat (every thread), plus cutime+cstime (short-lived children a
  process ran and reaped in the window, such as a ``ping``), in % of one core over the window;
* RSS (VmRSS) and PSS (/proc/<pid>/smaps_rollup) at the window's end; PSS shares pages between the
  processes that map them, so its total is what the processes cost together, RSS's is not;
* wake-ups: voluntary context switches per second (the process blocked and was woken: a timer, a
  message, a poll), and involuntary ones (preempted: they grow with the machine's load). They are
  summed over /proc/<pid>/task/*/status, since /proc/<pid>/status counts the main thread alone.

Each process is named by its command line (dc-bringup, destination_server, measurement_server,
group_server, image_services, "servers (one process)" under ``--single-process``, dc sim, or its
executable). With --sim, ``dc sim`` runs in the same
environment during the whole measurement; its own cost is reported apart and not in DC's total.
``--compressed-camera FPS`` runs, beside them, a publisher of a synthetic sensor_msgs/CompressedImage on
/camera/image_raw/compressed (reliable, depth 10, as image_transport publishes; --compressed-kb of random
bytes, which no JPEG encoder would shrink further), for a job that records a camera (dc sim has none); it is
not counted in DC's total either. ``--use-sim-time`` makes every server take the simulator's 50 Hz /clock,
which a robot does not publish: with the simulator, measure both (two modes) and read the one without it as the robot's.

    .venv/bin/python benchmarks/footprint.py [--params FILE]... [--mode NAME [--bringup-args ARGS]]...
        [--extra-args ARGS] [--sim [--sim-args ARGS]] [--settle 20] [--window 60] [--runs 1] [--label L]

    .venv/bin/python benchmarks/footprint.py --runs 3 --label default      # params/default.yaml
    .venv/bin/python benchmarks/footprint.py --params params/benchmarks/robot_footprint.yaml --sim \\
        --mode wall --mode sim-time --bringup-args "--use-sim-time" --runs 3 --label robot

A table per parameter file and mode (medians of --runs) goes to stdout, every run to
benchmarks/results/footprint_<date>[_<label>].json. dc-bringup is stopped with SIGTERM (its
servers in order), then SIGKILL after --stop-timeout; every wait is bounded.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import platform
import random
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import FrameType
from typing import Any, TextIO

# The repository's root: benchmarks/ is a namespace package there, which mypy resolves as well.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import end_to_end as e2e  # a sibling script
from dc_bringup.launcher import LOG_LEVELS
from dc_bringup.launcher import build_parser as build_bringup_parser
from dc_bringup.validate import SERVER_MODULES

REPO = e2e.REPO
COMPRESSED_CAMERA = r"""
import os, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage
fps, size = float(sys.argv[1]), int(sys.argv[2])
rclpy.init()
node = rclpy.create_node("bench_compressed_camera")
publisher = node.create_publisher(
    CompressedImage, "/camera/image_raw/compressed", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
)
frames = [os.urandom(size) for _ in range(8)]
start, sent = time.monotonic(), 0
try:
    while True:
        now = time.monotonic()
        if sent < (now - start) * fps:
            message = CompressedImage(format="jpeg", data=frames[sent % len(frames)])
            message.header.stamp.sec, message.header.stamp.nanosec = divmod(time.time_ns(), 1_000_000_000)
            publisher.publish(message)
            sent += 1
        else:
            time.sleep(start + sent / fps - now)
except Exception:  # stopped with SIGTERM: rclpy's context is gone
    pass
"""
CLK_TCK = os.sysconf("SC_CLK_TCK")
UP_LINE = "DC is up"
SERVER_NAMES = {module: name for name, module in SERVER_MODULES.items()}
SERVER_NAMES["dc_bringup.single_process"] = "servers (one process)"
# Options whose value is itself a command line: "--bringup-args --use-sim-time" must not be read
# by argparse as two options.
COMMAND_LINE_OPTIONS = ("--bringup-args", "--extra-args", "--sim-args")
BYTES_PER_MB = 1024 * 1024


# ---------------------------------------------------------------------------------------------
# /proc readings
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ThreadCounts:
    name: str  # /proc/<pid>/task/<tid>/comm
    voluntary: int
    involuntary: int


@dataclass
class Reading:
    """One process at one instant."""

    pid: int
    start_ticks: int  # its start time: tells a reused pid from the process first seen
    name: str
    cpu_ticks: int  # utime + stime of all its threads, dead ones included
    reaped_ticks: int  # cutime + cstime: children it waited for
    threads: dict[int, ThreadCounts] = field(default_factory=dict)
    rss_kb: int = 0
    pss_kb: int = 0

    @property
    def key(self) -> tuple[int, int]:
        return self.pid, self.start_ticks


def _stat_fields(pid: int) -> list[str]:
    # The command name in parentheses may hold spaces: fields are counted after its closing one.
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def _status_values(path: Path, keys: Sequence[str]) -> dict[str, int]:
    values = {}
    for line in path.read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in keys:
            values[key] = int(rest.split()[0])
    return values


def process_name(pid: int) -> str:
    argv = [a for a in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0") if a]
    if not argv:
        return "?"
    for before, arg in itertools.pairwise(argv):
        if before == "-m" and arg in SERVER_NAMES:
            return SERVER_NAMES[arg]
    # Console scripts run as "python .venv/bin/dc-bringup ...": the script is the first or second word.
    for i, arg in enumerate(argv[:2]):
        base = Path(arg).name
        if base == "dc-bringup":
            return "dc-bringup"
        if base == "dc" and argv[i + 1 : i + 2] == ["sim"]:
            return "dc sim"
    return Path(argv[0]).name


def read_process(pid: int) -> Reading | None:
    """The process's counters now, or None when it is gone (it may exit while being read)."""
    try:
        fields = _stat_fields(pid)
        reading = Reading(
            pid=pid,
            start_ticks=int(fields[19]),  # starttime (field 22)
            name=process_name(pid),
            cpu_ticks=int(fields[11]) + int(fields[12]),  # utime, stime (fields 14, 15)
            reaped_ticks=int(fields[13]) + int(fields[14]),  # cutime, cstime (fields 16, 17)
        )
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(FileNotFoundError, ProcessLookupError):
                counts = _status_values(task / "status", ("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches"))
                reading.threads[int(task.name)] = ThreadCounts(
                    (task / "comm").read_text().strip(),
                    counts["voluntary_ctxt_switches"],
                    counts["nonvoluntary_ctxt_switches"],
                )
        reading.rss_kb = _status_values(Path(f"/proc/{pid}/status"), ("VmRSS",)).get("VmRSS", 0)
        reading.pss_kb = _status_values(Path(f"/proc/{pid}/smaps_rollup"), ("Pss",)).get("Pss", 0)
    except (FileNotFoundError, ProcessLookupError):
        return None
    return reading


def descendants(root: int) -> list[int]:
    """``root`` and every process below it, from one walk of /proc."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(FileNotFoundError, ProcessLookupError):
            children.setdefault(int(_stat_fields(int(entry.name))[1]), []).append(int(entry.name))
    found, queue = [], [root]
    while queue:
        pid = queue.pop()
        found.append(pid)
        queue.extend(children.get(pid, []))
    return found


def read_tree(root: int) -> dict[tuple[int, int], Reading]:
    readings = (read_process(pid) for pid in descendants(root))
    return {r.key: r for r in readings if r is not None}


def machine_ticks() -> tuple[int, int]:
    """(busy, total) jiffies of all CPUs since boot, from /proc/stat."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = values[3] + values[4]  # idle, iowait
    total = sum(values[:8])  # guest time is already in user
    return total - idle, total


# ---------------------------------------------------------------------------------------------
# figures of one window
# ---------------------------------------------------------------------------------------------


@dataclass
class ProcessFigures:
    """One named process (or several of the same name, summed) over the window."""

    name: str
    pids: list[int]
    cpu_percent: float
    rss_mb: float
    pss_mb: float
    wakeups_per_s: float
    involuntary_per_s: float
    threads: int


@dataclass
class ThreadFigures:
    process: str
    thread: str  # threads of one process with the same name are summed
    wakeups_per_s: float


def window_figures(
    before: dict[tuple[int, int], Reading], after: dict[tuple[int, int], Reading], seconds: float
) -> tuple[list[ProcessFigures], list[ThreadFigures]]:
    """Per process name: what the processes alive at the window's end cost during it.

    A process started in the window has all of its counters in it; one that ended in it is counted
    by its parent's reaped time when the parent is measured (its wake-ups are lost).
    """
    by_name: dict[str, ProcessFigures] = {}
    by_thread: dict[tuple[str, str], float] = {}
    for key, end in after.items():
        start = before.get(key)
        cpu = end.cpu_ticks + end.reaped_ticks - (start.cpu_ticks + start.reaped_ticks if start else 0)
        voluntary = involuntary = 0
        for tid, counts in end.threads.items():
            first = start.threads.get(tid) if start else None
            woke = counts.voluntary - (first.voluntary if first else 0)
            voluntary += woke
            involuntary += counts.involuntary - (first.involuntary if first else 0)
            thread_key = (end.name, counts.name)
            by_thread[thread_key] = by_thread.get(thread_key, 0.0) + woke / seconds
        figures = by_name.setdefault(end.name, ProcessFigures(end.name, [], 0.0, 0.0, 0.0, 0.0, 0.0, 0))
        figures.pids.append(end.pid)
        figures.cpu_percent += cpu / CLK_TCK / seconds * 100
        figures.rss_mb += end.rss_kb / 1024
        figures.pss_mb += end.pss_kb / 1024
        figures.wakeups_per_s += voluntary / seconds
        figures.involuntary_per_s += involuntary / seconds
        figures.threads += len(end.threads)
    threads = [ThreadFigures(p, t, w) for (p, t), w in sorted(by_thread.items(), key=lambda item: -item[1])]
    return list(by_name.values()), threads


def total(processes: list[ProcessFigures], name: str = "total") -> ProcessFigures:
    return ProcessFigures(
        name,
        [pid for p in processes for pid in p.pids],
        sum(p.cpu_percent for p in processes),
        sum(p.rss_mb for p in processes),
        sum(p.pss_mb for p in processes),
        sum(p.wakeups_per_s for p in processes),
        sum(p.involuntary_per_s for p in processes),
        sum(p.threads for p in processes),
    )


@dataclass
class Measurement:
    """One parameter file in one mode, one run."""

    params: str
    mode: str
    bringup_args: list[str]
    run: int
    domain: int
    up_s: float  # dc-bringup started → "DC is up"
    window_s: float
    processes: list[ProcessFigures]
    total: ProcessFigures
    sim: list[ProcessFigures]
    threads: list[ThreadFigures]  # DC's threads, most wake-ups first
    machine_busy_percent: float  # of all CPUs over the window, DC included
    loadavg: tuple[float, float]  # 1-minute load at the window's start and end
    stop_s: float = 0.0  # SIGTERM → dc-bringup exited
    exit_code: int | None = None  # None: it had to be killed
    log_errors: int = 0  # "[ERROR]" lines dc-bringup and its servers wrote to stderr
    log_warnings: int = 0  # "[WARN]" lines
    warnings: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------
# processes
# ---------------------------------------------------------------------------------------------


def venv_script(name: str) -> str:
    # Not resolved: .venv/bin/python is a symlink, and the scripts live beside the link.
    return str(Path(sys.executable).parent / name)


class Started:
    """A process tree started by this script, stopped with everything still running below it."""

    def __init__(self, argv: list[str], env: dict[str, str], cwd: Path, log: Path) -> None:
        self.log = log
        with log.open("w") as stderr:
            # A session of its own: a Ctrl-C in this terminal reaches this script, which stops it in order.
            self.process = subprocess.Popen(
                argv,
                env=env,
                cwd=cwd,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=stderr,
                start_new_session=True,
            )
        self.started = time.monotonic()
        self.seen: dict[int, int] = {}  # pid → start ticks of every descendant read, to clean up by pid

    @property
    def pid(self) -> int:
        return self.process.pid

    def read(self) -> dict[tuple[int, int], Reading]:
        readings = read_tree(self.pid)
        self.seen.update(r.key for r in readings.values())
        return readings

    def log_text(self) -> str:
        return self.log.read_text(errors="replace")

    def stop(self, timeout: float) -> tuple[int | None, float]:
        """SIGTERM, then SIGKILL after ``timeout``; then any descendant left. (exit code or None, seconds)."""
        with contextlib.suppress(FileNotFoundError, ProcessLookupError):
            self.seen.update(r.key for r in read_tree(self.pid).values())
        started = time.monotonic()
        code: int | None = None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                code = self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        else:
            code = self.process.returncode
        seconds = time.monotonic() - started
        # Servers get SIGTERM when dc-bringup dies; one that outlives it by 10 s is killed, by pid,
        # only if that pid is still the process seen (not a reused one).
        deadline = time.monotonic() + 10.0
        for pid, start_ticks in self.seen.items():
            while _alive(pid, start_ticks) and time.monotonic() < deadline:
                time.sleep(0.1)
            if _alive(pid, start_ticks):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        return code, seconds


def _alive(pid: int, start_ticks: int) -> bool:
    try:
        fields = _stat_fields(pid)
    except (FileNotFoundError, ProcessLookupError):
        return False
    return int(fields[19]) == start_ticks and fields[0] != "Z"


@contextlib.contextmanager
def started(argv: list[str], env: dict[str, str], cwd: Path, log: Path, stop_timeout: float) -> Iterator[Started]:
    process = Started(argv, env, cwd, log)
    try:
        yield process
    finally:
        process.stop(stop_timeout)


def wait_for_up(bringup: Started, timeout: float) -> float:
    """Seconds until dc-bringup logs that DC is up; raises if it exits or the time runs out."""
    deadline = bringup.started + timeout
    while time.monotonic() < deadline:
        if UP_LINE in bringup.log_text():
            return time.monotonic() - bringup.started
        if bringup.process.poll() is not None:
            raise RuntimeError(f"dc-bringup exited with {bringup.process.returncode}:\n{_tail(bringup.log)}")
        time.sleep(0.1)
    raise RuntimeError(f"dc-bringup did not log {UP_LINE!r} within {timeout:g} s:\n{_tail(bringup.log)}")


def _tail(log: Path, lines: int = 15) -> str:
    return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])


# ---------------------------------------------------------------------------------------------
# one measurement
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Mode:
    name: str
    args: tuple[str, ...] = ()


def environment(home: Path, domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        HOME=str(home),
        ROS_DOMAIN_ID=str(domain),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(home / "roslog"),
        RCUTILS_COLORIZED_OUTPUT="0",
    )
    return env


PROBE = """
import time, rclpy
rclpy.init()
node = rclpy.create_node("dc_footprint_probe")
time.sleep({seconds})
print(len(node.get_node_names_and_namespaces()) - 1)
"""


def quiet_domain(first: int, env: dict[str, str], tries: int = 10, seconds: float = 2.0) -> int:
    """The first ROS domain from ``first`` where no node answers: other DC stacks on this machine
    (tests, benchmarks) pick random domains too, and one sharing ours would drive our servers."""
    for domain in range(first, first + tries):
        probe = subprocess.run(
            [sys.executable, "-c", PROBE.format(seconds=seconds)],
            env={**env, "ROS_DOMAIN_ID": str(domain)},
            capture_output=True,
            text=True,
            timeout=60.0,
            check=False,
        )
        if probe.returncode == 0 and probe.stdout.strip() == "0":
            return domain
        print(
            f"ROS domain {domain} is in use ({probe.stdout.strip() or probe.stderr.strip()[-200:]}), next", flush=True
        )
    raise RuntimeError(f"no quiet ROS domain in {first}..{first + tries - 1}")


def measure(workdir: Path, params: Path, mode: Mode, run: int, domain: int, args: argparse.Namespace) -> Measurement:
    home = workdir / f"run{run}-{params.stem}-{mode.name}"
    home.mkdir()
    env = environment(home, domain)
    domain = quiet_domain(domain, env)
    env["ROS_DOMAIN_ID"] = str(domain)
    warnings: list[str] = []
    with contextlib.ExitStack() as stack:
        sim: Started | None = None
        if args.sim:
            # Started first, so that /map, /tf and /clock are there when the measurements start.
            sim_argv = [venv_script("dc"), "sim", *shlex.split(args.sim_args)]
            sim = stack.enter_context(started(sim_argv, env, home, home / "sim.log", 10.0))
        if args.compressed_camera > 0:
            camera_argv = [
                sys.executable,
                "-c",
                COMPRESSED_CAMERA,
                str(args.compressed_camera),
                str(int(args.compressed_kb * 1000)),
            ]
            stack.enter_context(started(camera_argv, env, home, home / "camera.log", 10.0))
        bringup_argv = [venv_script("dc-bringup"), str(params), *shlex.split(args.extra_args), *mode.args]
        bringup = Started(bringup_argv, env, home, home / "dc-bringup.log")
        try:
            up_s = wait_for_up(bringup, args.start_timeout)
            time.sleep(args.settle)
            if bringup.process.poll() is not None:
                raise RuntimeError(f"dc-bringup exited during the settle time:\n{_tail(bringup.log)}")
            busy0, all0 = machine_ticks()
            load0 = os.getloadavg()[0]
            t0 = time.monotonic()
            before = bringup.read()
            sim_before = sim.read() if sim else {}
            time.sleep(args.window)
            t1 = time.monotonic()
            after = bringup.read()
            sim_after = sim.read() if sim else {}
            busy1, all1 = machine_ticks()
            load1 = os.getloadavg()[0]
            if bringup.process.poll() is not None:
                raise RuntimeError(f"dc-bringup exited during the window:\n{_tail(bringup.log)}")
            # Only servers: a child such as a ping may end between the two readings as it should.
            servers = ("dc-bringup", *SERVER_MODULES)
            gone = sorted(f"{r.name} ({r.pid})" for key, r in before.items() if key not in after and r.name in servers)
            if gone:
                warnings.append("ended during the window (a restart?): " + ", ".join(gone))
            if sim is not None and sim.process.poll() is not None:
                warnings.append(f"dc sim exited with {sim.process.returncode} before the window's end")
        except BaseException:
            bringup.stop(args.stop_timeout)
            raise
        exit_code, stop_s = bringup.stop(args.stop_timeout)
    window_s = t1 - t0
    processes, threads = window_figures(before, after, window_s)
    sim_figures, _ = window_figures(sim_before, sim_after, window_s)
    log = bringup.log_text()
    measurement = Measurement(
        params=_display(params),
        mode=mode.name,
        bringup_args=[*shlex.split(args.extra_args), *mode.args],
        run=run,
        domain=domain,
        up_s=up_s,
        window_s=window_s,
        processes=sorted(processes, key=_process_order),
        total=total(processes),
        sim=sim_figures,
        threads=threads,
        machine_busy_percent=(busy1 - busy0) / max(all1 - all0, 1) * 100,
        loadavg=(load0, load1),
        stop_s=stop_s,
        exit_code=exit_code,
        log_errors=log.count("[ERROR]"),
        log_warnings=log.count("[WARN]"),
        warnings=warnings,
    )
    if exit_code != 0:
        measurement.warnings.append(f"dc-bringup exited with {exit_code} on SIGTERM (None: killed)")
    for level, count in (("[ERROR]", measurement.log_errors), ("[WARN]", measurement.log_warnings)):
        if count:
            first = next(line for line in log.splitlines() if level in line)
            measurement.warnings.append(f"{count} {level} line(s) in dc-bringup's log, the first: {first[:200]}")
    return measurement


def _process_order(p: ProcessFigures) -> tuple[int, str]:
    known = ["dc-bringup", *SERVER_MODULES]
    return (known.index(p.name), "") if p.name in known else (len(known), p.name)


def _display(path: Path) -> str:
    with contextlib.suppress(ValueError):
        return str(path.relative_to(REPO))
    return str(path)


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------

FIGURES = ("cpu_percent", "rss_mb", "pss_mb", "wakeups_per_s", "involuntary_per_s", "threads")


def median_rows(rows: list[list[ProcessFigures]]) -> list[dict[str, Any]]:
    """Per process name, the median of each figure over the runs where it ran."""
    names: list[str] = []
    for row in rows:
        names += [p.name for p in row if p.name not in names]
    medians = []
    for name in names:
        found = [p for row in rows for p in row if p.name == name]
        medians.append(
            {"name": name, "runs": len(found), **{f: statistics.median(getattr(p, f) for p in found) for f in FIGURES}}
        )
    return medians


def summarise(measurements: list[Measurement]) -> list[dict[str, Any]]:
    groups: dict[tuple[str, str], list[Measurement]] = {}
    for m in measurements:
        groups.setdefault((m.params, m.mode), []).append(m)
    summary = []
    for (params, mode), ms in groups.items():
        thread_names: dict[tuple[str, str], list[float]] = {}
        for m in ms:
            for t in m.threads:
                thread_names.setdefault((t.process, t.thread), []).append(t.wakeups_per_s)
        # A thread missing from a run woke 0 times there.
        threads = sorted(
            ((p, t, statistics.median(v + [0.0] * (len(ms) - len(v)))) for (p, t), v in thread_names.items()),
            key=lambda item: -item[2],
        )
        summary.append(
            {
                "params": params,
                "mode": mode,
                "bringup_args": ms[0].bringup_args,
                "runs": len(ms),
                "processes": median_rows([m.processes for m in ms]),
                "total": median_rows([[m.total] for m in ms])[0],
                "sim": median_rows([m.sim for m in ms]),
                "threads": [{"process": p, "thread": t, "wakeups_per_s": w} for p, t, w in threads],
                "up_s": statistics.median(m.up_s for m in ms),
                "stop_s": statistics.median(m.stop_s for m in ms),
                "machine_busy_percent": statistics.median(m.machine_busy_percent for m in ms),
                "warnings": sorted({w for m in ms for w in m.warnings}),
            }
        )
    return summary


def _row(row: dict[str, Any], name: str | None = None) -> str:
    return (
        f"  {name or row['name']:<24} {row['cpu_percent']:6.2f} {row['rss_mb']:7.1f} {row['pss_mb']:7.1f} "
        f"{row['wakeups_per_s']:10.1f} {row['involuntary_per_s']:8.1f} {row['threads']:7.0f}"
    )


def print_report(summary: list[dict[str, Any]], args: argparse.Namespace, out: TextIO = sys.stdout) -> None:
    header = f"  {'process':<24} {'CPU %':>6} {'RSS MB':>7} {'PSS MB':>7} {'wakeups/s':>10} {'invol/s':>8} threads"
    for s in summary:
        args_text = shlex.join(s["bringup_args"]) or "no extra arguments"
        print(
            f"\n{s['params']}, mode {s['mode']} ({args_text}): medians of {s['runs']} run(s), "
            f"window {args.window:g} s after {args.settle:g} s settle; up in {s['up_s']:.1f} s, "
            f"stopped in {s['stop_s']:.1f} s; machine busy {s['machine_busy_percent']:.0f} % of "
            f"{os.cpu_count()} CPUs",
            file=out,
        )
        print(header, file=out)
        for row in s["processes"]:
            print(_row(row), file=out)
        print(_row(s["total"], "total DC"), file=out)
        for row in s["sim"]:
            print(_row(row, f"{row['name']} (not in total)"), file=out)
        busiest = ", ".join(f"{t['process']}/{t['thread']} {t['wakeups_per_s']:.1f}" for t in s["threads"][:5])
        print(f"  most wake-ups/s by thread: {busiest}", file=out)
        for warning in s["warnings"]:
            print(f"  warning: {warning}", file=out)
    if len(summary) > 1:
        print(f"\n  {'params':<40} {'mode':<14} {'CPU %':>6} {'PSS MB':>7} {'wakeups/s':>10} {'procs':>5}", file=out)
        for s in summary:
            t = s["total"]
            procs = len(s["processes"])
            print(
                f"  {s['params']:<40} {s['mode']:<14} {t['cpu_percent']:6.2f} {t['pss_mb']:7.1f} "
                f"{t['wakeups_per_s']:10.1f} {procs:5d}",
                file=out,
            )


# ---------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------


# While parsing, a mode is (name, its dc-bringup arguments or None until --bringup-args gives them).
_ParsedModes = list[tuple[str, tuple[str, ...] | None]]


class _AddMode(argparse.Action):
    def __call__(
        self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any, option: str | None = None
    ) -> None:
        modes: _ParsedModes = namespace.modes or []
        if any(name == values for name, _ in modes):
            parser.error(f"--mode {values} given twice")
        namespace.modes = [*modes, (str(values), None)]


class _ModeArgs(argparse.Action):
    """--bringup-args belongs to the --mode before it (without one, to the single mode "default")."""

    def __call__(
        self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any, option: str | None = None
    ) -> None:
        modes: _ParsedModes = namespace.modes or [("default", None)]
        name, given = modes[-1]
        if given is not None:
            parser.error(f"--bringup-args given twice for mode {name}")
        namespace.modes = [*modes[:-1], (name, tuple(shlex.split(str(values))))]


def _join_command_line_values(argv: Sequence[str]) -> list[str]:
    joined: list[str] = []
    items = iter(argv)
    for item in items:
        if item in COMMAND_LINE_OPTIONS:
            value = next(items, None)
            joined.append(item if value is None else f"{item}={value}")
        else:
            joined.append(item)
    return joined


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--params", action="append", type=Path, help="parameter file to start (repeatable; params/default.yaml)"
    )
    parser.add_argument("--mode", action=_AddMode, dest="modes", help="a name for the --bringup-args that follow")
    parser.add_argument(
        "--bringup-args", action=_ModeArgs, dest="modes", metavar="ARGS", help="dc-bringup arguments of the mode before"
    )
    parser.add_argument("--extra-args", default="", metavar="ARGS", help="dc-bringup arguments of every mode")
    parser.add_argument("--sim", action="store_true", help="run `dc sim` beside DC (not counted in DC's total)")
    parser.add_argument(
        "--sim-args",
        default="--clock --loop --camera-fps 0",
        metavar="ARGS",
        help="arguments of `dc sim` (default: %(default)s; no camera, as the robot job reads none)",
    )
    parser.add_argument(
        "--compressed-camera",
        type=float,
        default=0.0,
        metavar="FPS",
        help="publish a synthetic sensor_msgs/CompressedImage on /camera/image_raw/compressed at FPS (not counted)",
    )
    parser.add_argument("--compressed-kb", type=float, default=50.0, help="size of each compressed frame (kB)")
    parser.add_argument("--settle", type=float, default=20.0, help="seconds after 'DC is up' before the window")
    parser.add_argument("--window", type=float, default=60.0, help="seconds measured")
    parser.add_argument("--runs", type=int, default=1, help="repeat every parameter file and mode; medians")
    parser.add_argument("--label", default="", help="appended to the JSON file's name")
    parser.add_argument("--json", type=Path, help="JSON output (benchmarks/results/footprint_<date>[_<label>].json)")
    parser.add_argument(
        "--domain", type=int, default=random.randint(100, 180), help="first ROS_DOMAIN_ID (one per measurement)"
    )
    parser.add_argument("--start-timeout", type=float, default=120.0, help="seconds allowed until 'DC is up'")
    parser.add_argument("--stop-timeout", type=float, default=60.0, help="seconds dc-bringup gets to stop on SIGTERM")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder (logs, records) and print it")
    args = parser.parse_args(_join_command_line_values(argv))
    args.params = [p.resolve() for p in args.params or [REPO / "params" / "default.yaml"]]
    parsed: _ParsedModes = args.modes or [("default", None)]
    args.modes = [Mode(name, given or ()) for name, given in parsed]
    for params in args.params:
        if not params.is_file():
            parser.error(f"--params {params}: no such file")
    for mode in args.modes:
        # parse_known_args: a mode may pass options this version of dc-bringup does not know yet.
        bringup, _ = build_bringup_parser().parse_known_args(["params.yaml", *shlex.split(args.extra_args), *mode.args])
        if LOG_LEVELS.index(bringup.log_level) > LOG_LEVELS.index("info"):
            parser.error(f"mode {mode.name}: --log-level {bringup.log_level} hides the {UP_LINE!r} line waited for")
    if args.runs < 1 or args.window <= 0 or args.settle < 0:
        parser.error("--runs must be at least 1, --window positive, --settle not negative")
    return args


def _stop_on_sigterm(signum: int, frame: FrameType | None) -> None:
    # As a Ctrl-C: the finally blocks stop what was started.
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    started_at = datetime.now(UTC)
    cases = [(params, mode) for params in args.params for mode in args.modes]
    measurements: list[Measurement] = []
    failure = ""
    domain = args.domain
    tmp = Path(tempfile.mkdtemp(prefix="dc-bench-footprint-"))
    try:
        for run in range(1, args.runs + 1):
            # Each run starts with another case: a drift of the machine does not favour one of them.
            shift = (run - 1) % len(cases)
            for params, mode in cases[shift:] + cases[:shift]:
                try:
                    m = measure(tmp, params, mode, run, domain, args)
                except RuntimeError as exc:
                    failure = f"run {run}, {_display(params)}, mode {mode.name}: {exc}"
                    break
                # A domain per measurement: a process that outlived its run cannot talk to the next one.
                domain = m.domain + 1
                measurements.append(m)
                print(
                    f"run {run}: {m.params} {m.mode}: DC {m.total.cpu_percent:.2f} % CPU, "
                    f"PSS {m.total.pss_mb:.1f} MB, {m.total.wakeups_per_s:.1f} wakeups/s "
                    f"({len(m.processes)} processes, machine busy {m.machine_busy_percent:.0f} %)",
                    flush=True,
                )
            if failure:
                break
    finally:
        if args.keep:
            print(f"kept: {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    if failure:
        print(f"footprint: {failure}", file=sys.stderr)
        if not measurements:
            return 1
    summary = summarise(measurements)
    print_report(summary, args)
    document = {
        "date": started_at.isoformat(timespec="seconds"),
        "machine": {
            "cpus": os.cpu_count(),
            "processor": e2e._processor(),
            "python": platform.python_version(),
            "kernel": platform.release(),
        },
        "settings": {
            "params": [_display(p) for p in args.params],
            "modes": [{"name": m.name, "bringup_args": list(m.args)} for m in args.modes],
            "extra_args": args.extra_args,
            "sim": args.sim,
            "sim_args": args.sim_args if args.sim else None,
            "compressed_camera": (
                {"fps": args.compressed_camera, "kb": args.compressed_kb} if args.compressed_camera > 0 else None
            ),
            "settle_s": args.settle,
            "window_s": args.window,
            "runs": args.runs,
            "label": args.label,
        },
        "incomplete": failure or None,
        "medians": summary,
        "measurements": [asdict(m) for m in measurements],
    }
    suffix = f"_{args.label}" if args.label else ""
    path = args.json or REPO / "benchmarks" / "results" / f"footprint_{started_at:%Y-%m-%d}{suffix}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nJSON: {_display(path.resolve())}")
    return 1 if failure else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # what was started is stopped by then; the traceback would say nothing more
        print("footprint: interrupted", file=sys.stderr)
        sys.exit(130)
