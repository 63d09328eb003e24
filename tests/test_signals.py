"""Bursts of stop signals never hang a DC process (issue 33, item 5).

The handler a server process installs (dc_core.lifecycle.init_server_process) used to call
``threading.Event.set``, which takes a lock: a second signal arriving while the first handler held it
deadlocked the main thread (2 of 10 runs with 30 SIGTERMs). The handler now only sets a flag and
writes the wake-up socket (dc_core.signals).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

from dc_core.signals import StopRequest, wake_on_signals

# The issue asks for 50 runs; on the old handler a run hung about once in 30-50, so 150 make the test fail there nearly always.
RUNS = 150
SIGNALS_PER_RUN = 30
# A run ends within milliseconds of its first signal; a hung one never does.
RUN_DEADLINE_S = 10.0

# One process, RUNS times: rclpy and the stop request set up as a server process does, a node's
# wait woken by the signals, the loop ended by the stop (run_server's shape without a server's weight).
PROBE = """
import sys
import rclpy
from rclpy.executors import SingleThreadedExecutor
from dc_core.lifecycle import init_server_process
from dc_core.signals import wake_on_signals

for run in range(int(sys.argv[1])):
    stop = init_server_process("error")
    node = rclpy.create_node("signal_probe")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    guard = node.create_guard_condition(lambda: None)
    wake_on_signals(guard.trigger, stop)
    print(f"ready {run}", flush=True)
    while not stop.is_set():
        executor.spin_once(timeout_sec=5.0)
    executor.shutdown(timeout_sec=1.0)
    node.destroy_node()
    rclpy.shutdown()
    print(f"stopped {run}", flush=True)
"""


def _read_line(process: subprocess.Popen[str], timeout: float) -> str | None:
    """The next line of ``process``'s stdout, or None after ``timeout`` s."""
    line: list[str] = []
    reader = threading.Thread(target=lambda: line.append(process.stdout.readline() if process.stdout else ""))
    reader.daemon = True
    reader.start()
    reader.join(timeout)
    return line[0].strip() if line else None


def test_fifty_bursts_of_thirty_sigterms_never_hang_a_server_process() -> None:
    started = time.monotonic()
    process = subprocess.Popen(
        [sys.executable, "-c", PROBE, str(RUNS)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        for run in range(RUNS):
            assert _read_line(process, RUN_DEADLINE_S) == f"ready {run}", f"run {run} did not start"
            for _ in range(SIGNALS_PER_RUN):
                os.kill(process.pid, signal.SIGTERM)
            line = _read_line(process, RUN_DEADLINE_S)
            assert line == f"stopped {run}", f"run {run}: hung after {SIGNALS_PER_RUN} SIGTERMs ({line!r})"
        assert process.wait(RUN_DEADLINE_S) == 0
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
    elapsed = time.monotonic() - started
    print(f"\n{RUNS} runs of {SIGNALS_PER_RUN} SIGTERMs in {elapsed:.1f} s")


def test_a_stop_asked_by_a_signal_wakes_threads_waiting_for_it() -> None:
    stop = StopRequest()
    woken = threading.Event()
    previous = signal.getsignal(signal.SIGUSR1)
    previous_fd = signal.set_wakeup_fd(-1)
    try:
        stop.install([signal.SIGUSR1])
        wake_on_signals(woken.set, stop)
        waiter_saw: list[bool] = []
        waiter = threading.Thread(target=lambda: waiter_saw.append(stop.wait(10.0)))
        waiter.start()
        os.kill(os.getpid(), signal.SIGUSR1)
        waiter.join(10.0)
        assert waiter_saw == [True] and stop.is_set() and woken.wait(5.0)
        assert stop.signals == 1
    finally:
        signal.signal(signal.SIGUSR1, previous)
        signal.set_wakeup_fd(previous_fd)
