"""No thread dies silently, and nothing waiting in memory is lost at a stop without its number (issue 33, items 2 and 3).

Each kind of thread DC starts gets an exception injected (monkeypatch on the code it runs): it is
logged with its traceback, counted in ``thread_failures``, and the server reports itself unhealthy.
For the delivery threads the records end delivered or counted: delivered + counted = sent. The
restart by the lifecycle manager is tested end to end in tests/test_e2e_never_silent.py.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy

from dc_core.destination import OutgoingRecord
from dc_core.http_status import StatusServer, _Server
from dc_core.signals import StopRequest, wake_on_signals
from dc_core.supervision import Supervisor
from dc_core.testing import RecordingLogger
from dc_core.worker import Worker
from dc_destinations.buffer import SqliteBuffer
from dc_destinations.commit import GroupCommitter
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.sender import Sender
from dc_destinations.settings import DestinationDeliveryParams
from tests.fault_helpers import fill, tmpfs
from tests.test_delivery import Recorder, record, settings, wait_until


def _failure_lines(logger: RecordingLogger, thread: str) -> list[str]:
    return [line for line in logger.at("error") if f"thread {thread}" in line]


def _assert_logged_with_traceback(logger: RecordingLogger, thread: str, error: str) -> None:
    lines = _failure_lines(logger, thread)
    assert len(lines) == 1, logger.lines
    assert error in lines[0] and "Traceback (most recent call last)" in lines[0], lines[0]


class _RaiseOnce:
    """Wraps a method: its first call (after ``skip`` calls) raises ``RuntimeError("injected ...")``."""

    def __init__(self, original: Any, what: str, skip: int = 0) -> None:
        self.original, self.what, self.skip, self.raised = original, what, skip, threading.Event()

    def __get__(self, instance: Any, owner: Any) -> Any:
        def call(*args: Any, **kwargs: Any) -> Any:
            if not self.raised.is_set():
                if self.skip == 0:
                    self.raised.set()
                    raise RuntimeError(f"injected into {self.what}")
                self.skip -= 1
            return self.original(instance, *args, **kwargs)

        return call


# -- the rule itself ------------------------------------------------------------------------------------


def test_a_thread_that_raises_is_logged_with_its_traceback_counted_and_makes_its_server_unhealthy() -> None:
    logger = RecordingLogger()
    supervisor = Supervisor(logger)
    told: list[str] = []
    supervisor.add_listener(told.append)
    saved: list[BaseException] = []
    supervisor.start_thread(lambda: None, name="fine").join(5)
    assert not supervisor.unhealthy and supervisor.thread_failures == 0, "a thread that returns did not fail"

    def broken() -> None:
        raise ZeroDivisionError("division by zero")

    supervisor.start_thread(broken, name="broken", on_failure=saved.append).join(5)
    _assert_logged_with_traceback(logger, "broken", "ZeroDivisionError: division by zero")
    assert supervisor.thread_failures == 1 and supervisor.unhealthy
    assert told == ["thread broken: ZeroDivisionError: division by zero"]
    assert isinstance(saved[0], ZeroDivisionError)
    assert supervisor.metrics() == {
        "thread_failures": 1,
        "unhealthy": "thread broken: ZeroDivisionError: division by zero",
    }
    assert "dc_thread_failures_total 1" in supervisor.prometheus().splitlines()


# -- the delivery threads: writer and senders ------------------------------------------------------------


def test_a_writer_that_dies_is_seen_and_its_records_are_committed_at_the_stop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    logger = RecordingLogger()
    injected = _RaiseOnce(GroupCommitter._commit, "the writer's commit")
    monkeypatch.setattr(GroupCommitter, "_commit", injected)
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    sent = [record(n) for n in range(200)]
    try:
        for outgoing in sent[:50]:
            pipeline.submit("sink", outgoing)
        wait_until(lambda: not pipeline.healthy(), what="the pipeline unhealthy")
        _assert_logged_with_traceback(logger, "dc-delivery-writer", "RuntimeError: injected into the writer's commit")
        document = pipeline.status_document()
        assert document["threads"]["thread_failures"] == 1
        assert document["threads"]["unhealthy"].startswith("thread dc-delivery-writer: RuntimeError")
        assert "dc_thread_failures_total 1" in pipeline.prometheus().splitlines()
        for outgoing in sent[50:]:  # the writer is dead: these wait in memory
            pipeline.submit("sink", outgoing)
        assert pipeline.buffer_metrics()["intake_pending"] == 200, "the batch it held waits again, visibly"
    finally:
        pipeline.stop(grace=5.0)
    metrics = pipeline.metrics()["sink"]
    assert metrics["dropped"] == 0
    # The restart: a new pipeline on the same buffer delivers what the stop committed.
    again = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, logger)
    again.start()
    try:
        delivered = sink.wait_for(200)
    finally:
        again.stop(grace=1.0)
    assert sorted(r.record_id for r in delivered) == sorted(r.record_id for r in sent), "delivered + counted = sent"


def test_a_sender_that_dies_is_seen_and_its_queue_is_delivered_after_the_restart(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    logger = RecordingLogger()
    injected = _RaiseOnce(Sender._idle, "the sender's wait")
    monkeypatch.setattr(Sender, "_idle", injected)
    sink, other = Recorder(), Recorder("other")
    destinations = {"sink": (sink, DestinationDeliveryParams()), "other": (other, DestinationDeliveryParams())}
    pipeline = DeliveryPipeline(settings(tmp_path), destinations, logger)
    pipeline.start()
    sent = [record(n) for n in range(100)]
    try:
        wait_until(injected.raised.is_set, what="the injected failure")
        wait_until(lambda: not pipeline.healthy(), what="the pipeline unhealthy")
        died = next(line for line in logger.at("error") if "thread dc-sender-" in line)
        assert "RuntimeError: injected into the sender's wait" in died and "Traceback" in died
        for outgoing in sent:
            pipeline.submit_record([("sink", outgoing), ("other", outgoing)])
        # The other destination's sender lives on: one dead sender delays no one else.
        living = other if "dc-sender-sink" in died else sink
        living.wait_for(100)
        assert pipeline.flush_intake(5)
    finally:
        pipeline.stop(grace=1.0)
    assert pipeline.status_document()["threads"]["thread_failures"] == 1
    dead = sink if living is other else other
    again = DeliveryPipeline(settings(tmp_path), destinations, logger)
    again.start()
    try:
        delivered = dead.wait_for(100)
    finally:
        again.stop(grace=1.0)
    assert sorted(r.record_id for r in delivered) == sorted(r.record_id for r in sent), "delivered + counted = sent"


# -- the worker, the status server, the signal relay, the manager's services thread -------------------------


def test_a_failure_handing_over_a_finished_job_is_counted_and_the_worker_stays_usable() -> None:
    logger = RecordingLogger()
    supervisor = Supervisor(logger)
    wakes = [0]

    def wake() -> None:
        wakes[0] += 1
        if wakes[0] == 1:
            raise RuntimeError("injected into the wake-up")

    worker = Worker("probe-worker", wake, threads=1, supervisor=supervisor)
    try:
        results: list[Any] = []
        worker.submit(lambda: 1, lambda outcome: results.append(outcome.get()))
        assert worker.wait_idle(5.0), "a job whose hand-over failed still counts as finished"
        _assert_logged_with_traceback(logger, "probe-worker (handing over a finished job)", "injected into the wake-up")
        assert supervisor.thread_failures == 1 and supervisor.unhealthy
        worker.submit(lambda: 2, lambda outcome: results.append(outcome.get()))
        assert worker.wait_idle(5.0)
        worker.run_finished()
        assert results == [1, 2]
    finally:
        worker.shutdown()


def test_a_status_server_thread_that_dies_is_counted(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(self: Any, poll_interval: float = 0.5) -> None:
        raise OSError("injected into serve_forever")

    monkeypatch.setattr(_Server, "serve_forever", broken)
    logger = RecordingLogger()
    supervisor = Supervisor(logger)
    server = StatusServer(
        "127.0.0.1", 0, health=lambda: True, metrics=dict, prometheus=lambda: "", supervisor=supervisor
    )
    try:
        wait_until(lambda: supervisor.thread_failures == 1, what="the failure counted")
        _assert_logged_with_traceback(logger, "dc-status-http", "OSError: injected into serve_forever")
    finally:
        server._server.server_close()


def test_a_signal_relay_that_dies_is_counted() -> None:
    logger = RecordingLogger()
    supervisor = Supervisor(logger)
    stop = StopRequest()
    previous = signal.getsignal(signal.SIGUSR1)
    previous_fd = signal.set_wakeup_fd(-1)

    def wake() -> None:
        raise RuntimeError("injected into the wake-up")

    try:
        stop.install([signal.SIGUSR1])
        wake_on_signals(wake, stop, supervisor)
        os.kill(os.getpid(), signal.SIGUSR1)
        wait_until(lambda: supervisor.thread_failures == 1, what="the failure counted")
        _assert_logged_with_traceback(logger, "signal-wakeup", "RuntimeError: injected into the wake-up")
    finally:
        signal.signal(signal.SIGUSR1, previous)
        signal.set_wakeup_fd(previous_fd)


@pytest.fixture
def ros_context() -> Iterator[None]:
    """rclpy's default context, which the manager's executors use."""
    rclpy.init()
    try:
        yield
    finally:
        rclpy.shutdown()


@pytest.mark.usefixtures("ros_context")
def test_the_managers_services_thread_is_counted_and_started_again(monkeypatch: pytest.MonkeyPatch) -> None:
    from rclpy.executors import SingleThreadedExecutor

    from dc_bringup import manager as manager_module

    calls = [0]
    original = SingleThreadedExecutor.spin_once

    def spin_once(self: Any, timeout_sec: float | None = None) -> None:
        if threading.current_thread().name == "manager-services":
            calls[0] += 1
            if calls[0] == 1:
                raise RuntimeError("injected into the services' executor")
        original(self, timeout_sec=min(timeout_sec or 0.1, 0.1))

    monkeypatch.setattr(SingleThreadedExecutor, "spin_once", spin_once)
    manager = manager_module.LifecycleManager([], bond_timeout=5.0)
    try:
        wait_until(lambda: manager.supervisor.thread_failures == 1, what="the failure counted")
        wait_until(lambda: not manager._services_thread.is_alive(), what="the thread ended")
        manager.check_bonds()
        wait_until(lambda: calls[0] >= 2, what="the services thread serving again")
        assert manager._services_thread.is_alive()
    finally:
        manager.destroy_node()


# -- item 3: a stop loses nothing without a word ---------------------------------------------------------


def test_a_stop_during_a_flow_commits_what_waits_in_memory(tmp_path: Path) -> None:
    sink = Recorder()
    # Commits held back: records gather in memory as they would behind a slow disk.
    pipeline = DeliveryPipeline(
        settings(tmp_path, commit_interval=2.0), {"sink": (sink, DestinationDeliveryParams())}, RecordingLogger()
    )
    pipeline.start()
    sent = [record(n) for n in range(300)]
    pipeline.submit("sink", sent[0])
    time.sleep(0.1)  # the writer took record 0 and waits commit_interval before its commit
    for outgoing in sent[1:]:
        pipeline.submit("sink", outgoing)
    in_memory = pipeline.buffer_metrics()["intake_pending"]
    pipeline.stop(grace=0.0)
    assert in_memory > 0
    buffer = SqliteBuffer(tmp_path / "delivery.sqlite3")
    try:
        on_disk = buffer.stats("sink").rows
    finally:
        buffer.close()
    assert on_disk + len(sink.delivered) == 300, (in_memory, on_disk, len(sink.delivered))
    assert pipeline.metrics()["sink"]["dropped"] == 0


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    with tmpfs(tmp_path / "disk", "2m") as disk:
        yield disk


def test_records_that_cannot_be_committed_at_the_stop_are_counted_and_named_in_one_line(small_disk: Path) -> None:
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(small_disk), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    pipeline.submit("sink", record(0))
    sink.wait_for(1)
    wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="record 0 out of the buffer")
    fill(small_disk / "filler")
    padded = [
        OutgoingRecord(r.record_id, r.topic, r.stamp_ns, {**r.data, "pad": "x" * 2000})
        for r in (record(n) for n in range(1, 151))
    ]
    for outgoing in padded:
        pipeline.submit("sink", outgoing)
    wait_until(lambda: any("group commit failed" in line for _, line in logger.lines), what="a failed commit")
    started = time.monotonic()
    pipeline.stop(grace=0.5)
    assert time.monotonic() - started < 10.0, "a bounded wait"
    lost = [line for line in logger.at("error") if "could not be committed at the stop" in line]
    assert len(lost) == 1, logger.lines
    assert lost[0].startswith("delivery buffer: 150 records held in memory could not be committed"), lost[0]
    assert "database or disk is full" in lost[0]
    metrics = pipeline.metrics()["sink"]
    assert metrics["dropped"] == 150
    assert len(sink.delivered) + metrics["dropped"] == 151, "delivered + counted = sent"


def test_a_plugins_own_thread_runs_under_the_rule() -> None:
    from dc_core.testing import FakeContext

    context = FakeContext(name="camera")

    def supervise_ffmpeg() -> None:
        raise RuntimeError("injected into the plugin's thread")

    context.start_thread(supervise_ffmpeg, name="camera-ffmpeg").join(5)
    _assert_logged_with_traceback(context.logger, "camera-ffmpeg", "RuntimeError: injected into the plugin's thread")
    assert context.supervisor.thread_failures == 1 and context.supervisor.unhealthy


def test_a_writer_stuck_past_the_stop_wait_has_what_it_did_not_take_counted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dc_destinations import commit

    monkeypatch.setattr(commit, "STOP_COMMIT_WAIT_S", 0.5)
    entered, release = threading.Event(), threading.Event()
    original = GroupCommitter._commit

    def stuck(self: GroupCommitter, handoffs: Any) -> None:
        entered.set()
        release.wait(10)  # a disk that hangs rather than fails
        original(self, handoffs)

    monkeypatch.setattr(GroupCommitter, "_commit", stuck)
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    pipeline.submit("sink", record(0))
    assert entered.wait(5)
    for n in range(1, 100):
        pipeline.submit("sink", record(n))
    started = time.monotonic()
    try:
        pipeline.stop(grace=0.0)
        assert time.monotonic() - started < 5.0, "a bounded wait"
    finally:
        release.set()
    lost = [line for line in logger.at("error") if "could not be committed at the stop" in line]
    assert len(lost) == 1 and lost[0].startswith("delivery buffer: 99 records held in memory"), logger.lines
    assert "the writer did not finish within 0.5 s" in lost[0]
    # The batch it held meets a closed buffer once the disk answers: counted too.
    wait_until(lambda: pipeline.metrics()["sink"]["dropped"] == 100, what="the stuck batch counted")
    assert len(sink.delivered) + pipeline.metrics()["sink"]["dropped"] == 100, "delivered + counted = sent"
