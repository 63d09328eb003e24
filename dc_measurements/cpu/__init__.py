"""Cpu measurement: machine-wide CPU usage and the processes using the most CPU."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import psutil

from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param

# The shortest window the first sample is averaged over: collected at activation, a window of a few
# milliseconds holds no clock tick (10 ms each) and said 0 % whatever the load.
FIRST_WINDOW_S = 0.2


@dataclass(frozen=True, kw_only=True)
class CpuParams:
    max_processes: int = param(5, minimum=-1, doc="Processes listed in `sorted`; -1 omits `sorted`")
    cpu_min: float = param(5.0, minimum=-1, doc="Leave out processes below this CPU percent; -1 keeps all")


class _ProcessSample(NamedTuple):
    cpu_seconds: float
    at: float


def _busy_and_total(times: Any) -> tuple[float, float]:
    total = float(sum(times))
    idle = float(times.idle) + float(getattr(times, "iowait", 0.0))
    return total - idle, total


class Cpu(Measurement[CpuParams]):
    """Average CPU usage since the previous sample, process count and top processes by CPU."""

    def __init__(self, context: MeasurementContext, params: CpuParams) -> None:
        super().__init__(context, params)
        # Own snapshots instead of psutil.cpu_percent(None), whose state is module-wide and would be
        # shared (and reset) by every Cpu instance in the process.
        self._last_busy, self._last_total = _busy_and_total(psutil.cpu_times())
        self._window_start: float | None = time.monotonic()  # None once a first sample was taken
        self._last_processes: dict[tuple[int, float], _ProcessSample] = {}
        self._last_average = 0.0

    def on_activate(self) -> None:
        # Start the averaging window now, so the first collect covers a real interval.
        self._last_busy, self._last_total = _busy_and_total(psutil.cpu_times())
        self._window_start = time.monotonic()
        if self.params.max_processes != -1:
            self._process_usage()

    def collect(self) -> dict[str, Any]:
        record: dict[str, Any] = {"average": round(self._average(), 2), "processes": len(psutil.pids())}
        if self.params.max_processes != -1:
            record["sorted"] = self._top_processes()
        return record

    def _average(self) -> float:
        if self._window_start is not None:
            # Once per activation, at most FIRST_WINDOW_S: the one record that would otherwise lie.
            time.sleep(max(0.0, self._window_start + FIRST_WINDOW_S - time.monotonic()))
            self._window_start = None
        busy, total = _busy_and_total(psutil.cpu_times())
        d_busy, d_total = busy - self._last_busy, total - self._last_total
        if d_total <= 0:
            # No clock tick since the previous sample (collects closer than 10 ms): nothing new to say.
            return self._last_average
        self._last_busy, self._last_total = busy, total
        self._last_average = min(100.0, max(0.0, d_busy / d_total * 100.0))
        return self._last_average

    def _process_usage(self) -> list[tuple[float, psutil.Process]]:
        """(cpu percent since the previous sample, process) for every readable process."""
        now = time.monotonic()
        wall_now = time.time()
        seen: dict[tuple[int, float], _ProcessSample] = {}
        usage: list[tuple[float, psutil.Process]] = []
        for proc in psutil.process_iter():
            try:
                with proc.oneshot():
                    times = proc.cpu_times()
                    created = proc.create_time()
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
            cpu_seconds = times.user + times.system
            key = (proc.pid, created)  # a recycled pid has another start time
            previous = self._last_processes.get(key)
            if previous is not None and now > previous.at:
                percent = (cpu_seconds - previous.cpu_seconds) / (now - previous.at) * 100.0
            else:
                # First sight of the process: its average since it started.
                age = wall_now - created
                percent = cpu_seconds / age * 100.0 if age > 0 else 0.0
            seen[key] = _ProcessSample(cpu_seconds, now)
            usage.append((max(0.0, percent), proc))
        self._last_processes = seen
        return usage

    def _top_processes(self) -> list[dict[str, Any]]:
        usage = self._process_usage()
        usage.sort(key=lambda item: item[0], reverse=True)
        cpu_min = self.params.cpu_min
        top: list[dict[str, Any]] = []
        for percent, proc in usage:
            if len(top) >= self.params.max_processes:
                break
            if cpu_min >= 0 and percent < cpu_min:
                break  # sorted: every later process is below the threshold too
            entry = _describe(proc, percent)
            if entry is not None:
                top.append(entry)
        return top


def _describe(proc: psutil.Process, percent: float) -> dict[str, Any] | None:
    try:
        with proc.oneshot():
            cmdline = proc.cmdline()
            name = proc.name()
            rss = proc.memory_info().rss
            created = proc.create_time()
            user = proc.username()  # the numeric uid when it has no passwd entry
    except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
        return None
    return {
        "pid": proc.pid,
        "user": user,
        "cmd": " ".join(cmdline) if cmdline else f"[{name}]",
        "cpu": round(percent, 2),
        "ram": rss // 1024,
        "uptime": max(0, int(time.time() - created)),
    }
