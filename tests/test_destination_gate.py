"""The contract a destination plugin relies on to keep no lock: ``send`` never runs beside its
``on_deactivate`` or ``on_cleanup``, and a stop whose grace ends while ``send`` still runs is not
held up by it (dc_destinations.sender.Gate). Real buffer and sender threads; the plugin is the test's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

from dc_core.destination import Destination, OutgoingRecord, RetryableError, SendOutcome
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.connection import Connection
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.test_delivery import record, wait_until

LOG = RecordingLogger("test_destination_gate")
GRACE_S = 0.3
BATCH = 5


class OverlapDetector:
    """Counts what runs at the same time; ``overlaps`` > 0 once ``send`` and ``close`` did."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.running: set[str] = set()
        self.overlaps = 0

    def enter(self, what: str) -> None:
        with self._lock:
            if self.running:
                self.overlaps += 1
            self.running.add(what)

    def leave(self, what: str) -> None:
        with self._lock:
            self.running.discard(what)


class SlowSink(Destination[None]):
    """No lock of its own: one kept connection, a ``send`` that blocks until released (or stopping)."""

    def __init__(self, detector: OverlapDetector, *, wait_for_stopping: bool = False) -> None:
        super().__init__(FakeContext(name="slow", logger=LOG), None)
        self.detector = detector
        self.wait_for_stopping = wait_for_stopping
        self.release = threading.Event()
        self.in_send = threading.Event()
        self.delivered: set[str] = set()
        self.closed = 0
        self.connection = self.keep(Connection("sink", self._open, self._close, timeout=1.0))

    def _open(self) -> str:
        return "connected"

    def _close(self, connection: str) -> None:
        self.detector.enter("close")
        time.sleep(0.05)  # a close that takes a moment: long enough for an overlap to be seen
        self.closed += 1
        self.detector.leave("close")

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        self.detector.enter("send")
        try:
            self.connection.get()
            self.in_send.set()
            if self.wait_for_stopping:
                # A rate limit's wait, as Slack's: the server's stop ends it, the batch is retried.
                if self.stopping.wait(10.0):
                    raise RetryableError("stopping before the rate's slot")
            else:
                assert self.release.wait(10.0), "the test never released the send"
            self.delivered.update(r.record_id for r in batch)
            return None
        finally:
            self.detector.leave("send")


def start(tmp_path: Path, sink: SlowSink) -> DeliveryPipeline:
    settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=0.2)
    pipeline = DeliveryPipeline(settings, {"slow": (sink, DestinationDeliveryParams(batch_size=BATCH))}, LOG)
    pipeline.start()
    return pipeline


def deactivate(pipeline: DeliveryPipeline, sink: SlowSink) -> float:
    """The server's deactivate: stop delivery within the grace, then the plugin's hook; seconds it took."""
    began = time.monotonic()
    pipeline.stop(GRACE_S)
    pipeline.between_sends("slow", sink.on_deactivate)
    return time.monotonic() - began


def deliver_the_rest(tmp_path: Path, sink: SlowSink, sent: list[OutgoingRecord]) -> dict[str, int]:
    """A second start delivers what the first left in the buffer; the counters once all is accounted for."""
    sink.wait_for_stopping = False
    sink.release.set()
    pipeline = start(tmp_path, sink)
    try:
        wait_until(lambda: {r.record_id for r in sent} <= sink.delivered, what="every record delivered")
        metrics = pipeline.metrics()["slow"]
    finally:
        deactivate(pipeline, sink)
    return metrics


def test_a_deactivate_during_a_hanging_send_finishes_within_the_grace_and_closes_after_it(tmp_path: Path) -> None:
    detector = OverlapDetector()
    sink = SlowSink(detector)
    sent = [record(i) for i in range(3 * BATCH)]
    pipeline = start(tmp_path, sink)
    for r in sent:
        pipeline.submit("slow", r)
    assert sink.in_send.wait(10.0), "the first batch reached send()"

    took = deactivate(pipeline, sink)

    # The stop waits out its grace (and the sender's 1 s join margin), never the hanging send.
    assert took < GRACE_S + 1.0 + 1.0, took
    assert detector.overlaps == 0 and sink.closed == 0, "the connection is not closed under the send still running"
    sink.release.set()
    wait_until(lambda: sink.closed == 1, what="the close owed to the send that outlived the grace")
    assert not sink.connection.is_open

    metrics = deliver_the_rest(tmp_path, sink, sent)
    assert detector.overlaps == 0, "send() and close() never ran at the same time"
    # The batch that outlived the grace was sent again (same record_ids): delivered once each.
    counted = int(metrics.get("dead_lettered", 0)) + int(metrics.get("dropped", 0))
    assert len(sink.delivered & {r.record_id for r in sent}) + counted == len(sent)


def test_a_send_waiting_for_its_turn_returns_when_the_grace_ends(tmp_path: Path) -> None:
    """A send that waits on ``stopping`` (a rate limit) is told at the end of the grace; its records wait."""
    detector = OverlapDetector()
    sink = SlowSink(detector, wait_for_stopping=True)
    sent = [record(i) for i in range(2 * BATCH)]
    pipeline = start(tmp_path, sink)
    for r in sent:
        pipeline.submit("slow", r)
    assert sink.in_send.wait(10.0)

    took = deactivate(pipeline, sink)

    assert took < GRACE_S + 1.0 + 1.0, took
    wait_until(lambda: sink.closed == 1, what="the connection closed once the send returned")
    assert not sink.delivered, "the batch was retried, not delivered"
    metrics = deliver_the_rest(tmp_path, sink, sent)
    assert not sink.stopping.is_set(), "the next start clears it"
    assert detector.overlaps == 0
    counted = int(metrics.get("dead_lettered", 0)) + int(metrics.get("dropped", 0))
    assert len(sink.delivered & {r.record_id for r in sent}) + counted == len(sent)


def test_deactivate_between_sends_runs_at_once(tmp_path: Path) -> None:
    detector = OverlapDetector()
    sink = SlowSink(detector)
    sink.release.set()
    sent = [record(i) for i in range(BATCH)]
    pipeline = start(tmp_path, sink)
    for r in sent:
        pipeline.submit("slow", r)
    wait_until(lambda: {r.record_id for r in sent} <= sink.delivered, what="delivered")
    pipeline.stop(GRACE_S)
    assert pipeline.between_sends("slow", sink.on_deactivate) is True
    assert sink.closed == 1 and detector.overlaps == 0
    metrics = pipeline.metrics()["slow"]
    assert int(metrics["sent"]) == len(sent)
