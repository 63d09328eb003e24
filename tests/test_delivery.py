"""The delivery pipeline with in-test destinations: no ROS, no sleeps as synchronisation."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from dc_core.destination import Destination, OutgoingRecord, RejectedError, RetryableError, SendOutcome
from dc_core.records import parse_record
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.buffer import FILE_NAME, PendingRecord, SalvageStopped, SqliteBuffer
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.record_ids import new_record_id, uuid7
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from dc_destinations.storage import BufferInUse, default_storage_dir
from tests.buffer_damage import damage_pages
from tests.fault_helpers import fill, tmpfs

LOG = RecordingLogger("test_delivery")


class Recorder(Destination[None]):
    """Accepts everything, keeps what it got; ``behaviour`` decides the outcome of each call."""

    def __init__(self, name: str = "sink", behaviour: Callable[[int, Sequence[OutgoingRecord]], Any] | None = None):
        super().__init__(FakeContext(name=name, logger=LOG), None)
        self.behaviour = behaviour
        self.calls = 0
        self.delivered: list[OutgoingRecord] = []
        self.lock = threading.Lock()
        self.changed = threading.Condition(self.lock)

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        with self.lock:
            self.calls += 1
            call = self.calls
        outcome = self.behaviour(call, batch) if self.behaviour else None
        with self.lock:
            if isinstance(outcome, SendOutcome):
                failed = set(outcome.retry) | set(outcome.reject) | set(outcome.waiting)
                self.delivered.extend(r for i, r in enumerate(batch) if i not in failed)
            else:
                self.delivered.extend(batch)
            self.changed.notify_all()
        return outcome

    def wait_for(self, count: int, timeout: float = 10.0) -> list[OutgoingRecord]:
        deadline = time.monotonic() + timeout
        with self.lock:
            while len(self.delivered) < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"{self.context.name}: {len(self.delivered)} of {count} records delivered")
                self.changed.wait(left)
            return list(self.delivered)


def record(n: int, topic: str = "/dc/measurement/test") -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(rid, topic, n, {"n": n, "record_id": rid})


def settings(tmp_path: Path, **overrides: Any) -> DeliveryParams:
    values: dict[str, Any] = {
        "storage_path": str(tmp_path),
        "flush": 0.05,
        "scheduler_base": 1.0,
        "scheduler_cap": 8.0,
    }
    values.update(overrides)
    return DeliveryParams(**values)


def reject_all(call: int, batch: Sequence[OutgoingRecord]) -> None:
    raise RejectedError("400 Bad Request: field 'x' unknown")


def wait_until(predicate: Callable[[], bool], timeout: float = 60.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


class RecordedWaits:
    """Backoff waits recorded instead of slept."""

    def __init__(self) -> None:
        self.delays: list[float] = []

    def __call__(self, delay: float) -> bool:
        self.delays.append(delay)
        return False


def test_a_forked_child_draws_other_random_bits_than_its_parent() -> None:
    new_record_id()  # the parent's pool of random bytes is filled before the fork
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: its ids go to the parent through the pipe
        os.write(write_end, " ".join(new_record_id() for _ in range(20)).encode())
        os._exit(0)
    os.close(write_end)
    with os.fdopen(read_end) as pipe:
        child = pipe.read().split()
    os.waitpid(pid, 0)
    parent = [new_record_id() for _ in range(20)]
    random_bits = 2**62 - 1
    assert len(child) == 20
    assert not {uuid.UUID(i).int & random_bits for i in child} & {uuid.UUID(i).int & random_bits for i in parent}


def test_record_ids_are_uuid7_and_increase() -> None:
    ids = [new_record_id() for _ in range(5000)]
    assert len(set(ids)) == len(ids)
    assert ids == sorted(ids)
    assert all(str(uuid.UUID(i)) == i for i in ids), "not the text of the UUID it stands for"
    parsed = uuid.UUID(ids[0])
    assert parsed.version == 7
    assert parsed.variant == uuid.RFC_4122
    assert abs((uuid7().int >> 80) - time.time() * 1000) < 5000


def test_records_are_delivered_in_order_and_removed_from_the_buffer(tmp_path: Path) -> None:
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams(batch_size=7))}, LOG)
    started = time.time()
    pipeline.start()
    try:
        sent = [record(i) for i in range(100)]
        for r in sent:
            pipeline.submit("sink", r)
        got = sink.wait_for(100)
        assert [r.data for r in got] == [r.data for r in sent]
        assert [r.record_id for r in got] == [r.data["record_id"] for r in sent]
        assert max(sink.calls, 0) >= 100 // 7
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="empty buffer")
        metrics = pipeline.metrics()["sink"]
        assert metrics["received"] == 100 and metrics["sent"] == 100
        assert metrics["dropped"] == metrics["failed"] == metrics["dead_lettered"] == 0
        assert started <= metrics["last_delivery"] <= time.time() and metrics["last_error_time"] is None
    finally:
        pipeline.stop(grace=1.0)


def test_a_delivered_record_serialises_to_the_text_that_was_buffered(tmp_path: Path) -> None:
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    try:
        rid = new_record_id()
        data = {"date": 1.5, "name": "caméra ✓", "nested": {"list": [1, 2.0, None, True]}, "record_id": rid}
        pipeline.submit("sink", OutgoingRecord(rid, "/t", 1, data))
        (got,) = sink.wait_for(1)
    finally:
        pipeline.stop(grace=1.0)
    assert got.data == data
    assert got.json_text is not None  # from the buffer, not serialised again
    assert got.to_json() == json.dumps(data, ensure_ascii=False, separators=(",", ":"))


@pytest.mark.parametrize(
    "poison",
    [
        OutgoingRecord("poison", "/t", 5, {"t": "\udcff"}),  # a lone surrogate: not UTF-8
        OutgoingRecord("poison", "/t", 5, {"v": float("nan")}),  # NaN: not JSON
        OutgoingRecord("poison", "/t", 5, {"t": "x"}, json_text='{"t":"\udcff"}'),  # text given as is
        OutgoingRecord("poison", "/t", 2**64, {"t": "x"}),  # a stamp SQLite cannot store: append() fails
    ],
    ids=["lone-surrogate", "nan", "json-text", "stamp-overflow"],
)
def test_one_record_the_buffer_cannot_store_never_stops_the_others(tmp_path: Path, poison: OutgoingRecord) -> None:
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(
        settings(tmp_path, commit_interval=0.05), {"sink": (sink, DestinationDeliveryParams())}, logger
    )
    pipeline.start()
    try:
        for n in range(5):
            pipeline.submit_record([("sink", record(n))])
        pipeline.submit_record([("sink", poison)], ("/t", 5, 5))
        for n in range(5, 10):
            pipeline.submit_record([("sink", record(n))])
        delivered = sink.wait_for(10)
        assert [r.data["n"] for r in delivered] == list(range(10))
        assert pipeline.flush_intake(5.0)
        metrics = pipeline.metrics()["sink"]
        assert metrics["malformed"] == 1 and metrics["received"] == 11
        assert pipeline.healthy()
        assert ("/t", 5, 5) in pipeline.hop_keys(), "the poison record's key is kept: a replay is not new"
        (line,) = [line for level, line in logger.lines if "not valid UTF-8 JSON" in line]
        assert "record poison" in line
    finally:
        pipeline.stop(grace=1.0)


def test_retryable_failures_back_off_exponentially_then_deliver(tmp_path: Path) -> None:
    def fail_three_times(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if call <= 3:
            raise RetryableError("503 Service Unavailable")

    sink = Recorder(behaviour=fail_three_times)
    waits = RecordedWaits()
    pipeline = DeliveryPipeline(
        settings(tmp_path, scheduler_base=2.0, scheduler_cap=5.0),
        {"sink": (sink, DestinationDeliveryParams())},
        LOG,
        wait=waits,
        uniform=lambda low, high: high,  # the top of the jitter range, to see the exponential
    )
    pipeline.start()
    try:
        for i in range(10):
            pipeline.submit("sink", record(i))
        pipeline.flush_intake(5)
        sink.wait_for(10)
        wait_until(lambda: pipeline.metrics()["sink"]["sent"] == 10)
        assert waits.delays[:3] == [2.0, 4.0, 5.0]  # base, 2 * base, capped
        metrics = pipeline.metrics()["sink"]
        assert metrics["failed"] >= 3
        assert metrics["retried"] >= 3
        assert metrics["dead_lettered"] == 0
        assert "503" in metrics["last_error"] and metrics["last_error_time"] <= metrics["last_delivery"]
    finally:
        pipeline.stop(grace=1.0)


def test_a_record_waiting_for_another_destination_is_retried_without_a_failure(tmp_path: Path) -> None:
    # FilesMetrics' wait for MinIO's upload: the dashboard and dc status showed it as a failing destination.
    health_states: list[str] = []
    pipeline: DeliveryPipeline

    def not_uploaded_yet(call: int, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        health_states.append(pipeline.destination_health()["sink"]["state"])
        return SendOutcome(waiting={0: "waiting for minio to store a.pgm: no object a.pgm"}) if call <= 3 else None

    sink = Recorder(behaviour=not_uploaded_yet)
    waits = RecordedWaits()
    pipeline = DeliveryPipeline(
        settings(tmp_path), {"sink": (sink, DestinationDeliveryParams(batch_size=2))}, LOG, wait=waits
    )
    pipeline.start()
    try:
        pipeline.submit("sink", record(0))
        pipeline.submit("sink", record(1))
        pipeline.flush_intake(5)
        sink.wait_for(2)
        wait_until(lambda: pipeline.metrics()["sink"]["sent"] == 2)
        assert sink.calls == 4
        metrics = pipeline.metrics()["sink"]
        assert (metrics["failed"], metrics["retried"], metrics["dead_lettered"]) == (0, 3, 0)
        assert metrics["last_error"] == "" and metrics["last_error_time"] is None
        assert set(health_states) == {"ok"} and pipeline.destination_health()["sink"]["state"] == "ok"
        assert len(waits.delays) == 3, "tried again after the backoff, as a retry"
    finally:
        pipeline.stop(grace=1.0)


def _prefilled(tmp_path: Path, count: int) -> None:
    """Queue "sink" holding records n = 0 … count - 1, committed before any sender runs."""
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    texts = [f'{{"n":"{n:03d}"}}' for n in range(count)]  # 11 bytes each
    buffer.append({"sink": [PendingRecord(f"r{n}", "/t", n, text, checked=True) for n, text in enumerate(texts)]})
    buffer.close()


def _numbers(batch: Sequence[OutgoingRecord]) -> list[int]:
    return [int(r.data["n"]) for r in batch]


def test_the_next_batch_is_read_while_send_runs_and_order_is_kept(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _prefilled(tmp_path, 23)
    read_ahead = threading.Event()
    read_batch = SqliteBuffer.read_batch

    def spied(self: SqliteBuffer, destination: str, limit: int, *, after_id: int = 0) -> Any:
        rows = read_batch(self, destination, limit, after_id=after_id)
        if after_id:
            read_ahead.set()
        return rows

    monkeypatch.setattr(SqliteBuffer, "read_batch", spied)
    batches: list[list[int]] = []

    def send(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if call == 1:
            assert read_ahead.wait(5.0), "the next batch is read during send(), not after it"
        batches.append(_numbers(batch))

    sink = Recorder(behaviour=send)
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams(batch_size=5))}, LOG)
    pipeline.start()
    try:
        sink.wait_for(23)
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="empty buffer")
    finally:
        pipeline.stop(grace=1.0)
    assert batches == [list(range(n, min(n + 5, 23))) for n in range(0, 23, 5)]
    assert pipeline.metrics()["sink"]["sent"] == 23


def test_a_confirmed_batch_is_deleted_while_the_next_is_sent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _prefilled(tmp_path, 15)
    deletes: list[tuple[str, int]] = []  # (thread, rows)
    delete = SqliteBuffer.delete

    def spied(self: SqliteBuffer, destination: str, row_ids: Sequence[int]) -> int:
        deletes.append((threading.current_thread().name, len(row_ids)))
        return delete(self, destination, row_ids)

    monkeypatch.setattr(SqliteBuffer, "delete", spied)
    batches: list[list[int]] = []

    def send(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if call == 2:
            wait_until(lambda: len(deletes) == 1, 5.0, "the first batch deleted during the second send()")
        batches.append(_numbers(batch))

    sink = Recorder(behaviour=send)
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams(batch_size=5))}, LOG)
    pipeline.start()
    try:
        sink.wait_for(15)
        # The last batch is deleted before the sender waits for more: the queue shows it gone.
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="empty buffer")
        assert pipeline.metrics()["sink"]["sent"] == 15
    finally:
        pipeline.stop(grace=1.0)
    assert batches == [list(range(n, n + 5)) for n in range(0, 15, 5)]
    assert [thread.startswith("dc-read-sink") for thread, _ in deletes] == [True, True, False], deletes
    assert [rows for _, rows in deletes] == [5, 5, 5]


def test_a_retried_record_goes_again_before_the_batch_read_ahead(tmp_path: Path) -> None:
    _prefilled(tmp_path, 20)
    batches: list[list[int]] = []

    def busy_once(call: int, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        batches.append(_numbers(batch))
        return SendOutcome(retry={2: "busy"}) if call == 1 else None

    sink = Recorder(behaviour=busy_once)
    pipeline = DeliveryPipeline(
        settings(tmp_path), {"sink": (sink, DestinationDeliveryParams(batch_size=5))}, LOG, wait=RecordedWaits()
    )
    pipeline.start()
    try:
        sink.wait_for(20)
    finally:
        pipeline.stop(grace=1.0)
    assert batches[:2] == [[0, 1, 2, 3, 4], [2, 5, 6, 7, 8]], "the queue's head first, not what was read ahead"
    assert sorted(n for batch in batches for n in batch) == sorted([*range(20), 2])


def test_rows_dropped_by_the_size_limit_during_send_are_not_sent_from_the_batch_read_ahead(tmp_path: Path) -> None:
    _prefilled(tmp_path, 10)  # 110 bytes
    batches: list[list[int]] = []
    pipeline: DeliveryPipeline

    def crowd_out_during_first_send(call: int, batch: Sequence[OutgoingRecord]) -> None:
        batches.append(_numbers(batch))
        if call == 1:
            # Two records of 60 bytes into a queue limited to 135: the oldest 9 rows make room.
            for n in (100, 101):
                pipeline.submit("sink", OutgoingRecord(f"new{n}", "/t", n, {"n": n, "record_id": new_record_id()}))
            assert pipeline.flush_intake(5.0)

    sink = Recorder(behaviour=crowd_out_during_first_send)
    params = DestinationDeliveryParams(batch_size=5, storage_total_limit_size="135", when_full="drop_oldest")
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, params)}, LOG)
    pipeline.start()
    try:
        sink.wait_for(8)
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="empty buffer")
    finally:
        pipeline.stop(grace=1.0)
    # Rows 0 to 8 made room: 5 to 8 went, 0 to 4 were in the send, which succeeded: sent, not dropped.
    metrics = pipeline.metrics()["sink"]
    assert metrics["dropped"] == 4 and metrics["sent"] == 8
    assert batches == [[0, 1, 2, 3, 4], [9, 100, 101]], "rows 5 to 8 were dropped before they were sent"
    assert sum(len(b) for b in batches) + metrics["dropped"] == 12, "delivered + dropped = submitted"


def test_jitter_is_full(tmp_path: Path) -> None:
    draws: list[tuple[float, float]] = []

    def uniform(low: float, high: float) -> float:
        draws.append((low, high))
        return 0.0

    def always_fail(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if call <= 5:
            raise ConnectionError("refused")

    sink = Recorder(behaviour=always_fail)
    pipeline = DeliveryPipeline(
        settings(tmp_path, scheduler_base=1.0, scheduler_cap=100.0),
        {"sink": (sink, DestinationDeliveryParams())},
        LOG,
        wait=RecordedWaits(),
        uniform=uniform,
    )
    pipeline.start()
    try:
        pipeline.submit("sink", record(1))
        sink.wait_for(1)
        assert draws[:5] == [(0.0, 1.0), (0.0, 2.0), (0.0, 4.0), (0.0, 8.0), (0.0, 16.0)]
    finally:
        pipeline.stop(grace=1.0)


def test_permanent_rejection_goes_to_dead_letters_with_the_error(tmp_path: Path) -> None:
    sink = Recorder(behaviour=reject_all)
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    try:
        for i in range(3):
            pipeline.submit("sink", record(i))
        wait_until(lambda: pipeline.metrics()["sink"]["dead_lettered"] == 3, what="dead letters")
        metrics = pipeline.metrics()["sink"]
        assert metrics["sent"] == 0 and metrics["buffered"] == 0 and metrics["dead_letters"] == 3
    finally:
        pipeline.stop(grace=0.5)
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        letters = buffer.list_dead_letters("sink")
        assert [json.loads(d.payload)["n"] for d in letters] == [0, 1, 2]
        assert all("400 Bad Request" in d.error for d in letters)
    finally:
        buffer.close()


def test_a_record_from_the_intake_is_sent_without_being_parsed_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import dc_core.destination
    import dc_destinations.sender

    parsed: list[str] = []

    def counting_parse(text: str) -> dict[str, Any]:
        parsed.append(text)
        return parse_record(text)

    monkeypatch.setattr(dc_destinations.sender, "parse_record", counting_parse)
    monkeypatch.setattr(dc_core.destination, "parse_record", counting_parse)
    texts: list[str] = []
    sink = Recorder(behaviour=lambda call, batch: texts.extend(r.to_json() for r in batch))
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    try:
        sent = [record(n) for n in range(20)]
        for r in sent:
            pipeline.submit("sink", r)
        delivered = sink.wait_for(20)
    finally:
        pipeline.stop(grace=1.0)
    assert texts == [r.to_json() for r in sent]
    assert parsed == [], "to_json() is the stored text: nothing parsed"
    assert delivered[3].data == sent[3].data and delivered[3].data is delivered[3].data
    assert parsed == [sent[3].to_json()], "data: parsed when read, once"
    assert delivered == sent


def _buffer_with_nan_rows(path: Path, how: str) -> None:
    """A buffer of queue "sink" holding 0, an unreadable {"n": NaN} and 2, as ``how`` left it."""
    buffer = SqliteBuffer(path)
    texts = ['{"n":0}', '{"n":NaN}' if how == "unchecked" else '{"n":1}', '{"n":2}']
    checked = how != "unchecked"
    buffer.append({"sink": [PendingRecord(f"r{n}", "/t", n, text, checked) for n, text in enumerate(texts)]})
    buffer.close()
    conn = sqlite3.connect(path)
    if how == "older_dc":  # written before payload_crc existed
        conn.executescript(
            """ALTER TABLE q_1 DROP COLUMN payload_crc; UPDATE q_1 SET payload = '{"n":NaN}' WHERE record_id = 'r1';
               UPDATE meta SET value = '2' WHERE key = 'schema_version';"""
        )
    elif how == "edited":
        conn.execute("""UPDATE q_1 SET payload = '{"n":NaN}' WHERE record_id = 'r1'""")
        conn.commit()
    conn.close()


@pytest.mark.parametrize("how", ["older_dc", "edited", "unchecked"])
def test_an_unreadable_payload_in_the_buffer_is_dead_lettered_never_sent(tmp_path: Path, how: str) -> None:
    _buffer_with_nan_rows(tmp_path / FILE_NAME, how)
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    try:
        delivered = sink.wait_for(2)
        wait_until(lambda: pipeline.metrics()["sink"]["dead_lettered"] == 1, what="the dead letter")
    finally:
        pipeline.stop(grace=1.0)
    assert [r.to_json() for r in delivered] == ['{"n":0}', '{"n":2}']
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        (letter,) = buffer.list_dead_letters("sink")
    finally:
        buffer.close()
    assert letter.record_id == "r1" and letter.payload == '{"n":NaN}'
    assert letter.error.startswith("unreadable payload in the buffer: NaN is not a JSON number")


def test_a_json_text_given_as_is_is_checked_before_it_is_sent(tmp_path: Path) -> None:
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    try:
        pipeline.submit("sink", OutgoingRecord("poison", "/t", 1, {"n": 1.0}, json_text='{"n":NaN}'))
        pipeline.submit("sink", record(2))
        (delivered,) = sink.wait_for(1)
        wait_until(lambda: pipeline.metrics()["sink"]["dead_lettered"] == 1, what="the dead letter")
    finally:
        pipeline.stop(grace=1.0)
    assert delivered.data["n"] == 2


def test_dead_letters_are_bounded_the_oldest_deleted_counted_and_logged_once(tmp_path: Path) -> None:
    size = len(record(0).to_json().encode("utf-8"))  # the bytes a dead letter counts
    params = DestinationDeliveryParams(batch_size=1, dead_letter_limit_size=str(3 * size + size // 2))
    logger = RecordingLogger()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(behaviour=reject_all), params)}, logger)
    pipeline.start()
    try:
        for i in range(8):
            pipeline.submit("sink", record(i))
        wait_until(lambda: pipeline.metrics()["sink"]["dead_lettered"] == 8, what="dead letters")
        metrics = pipeline.metrics()["sink"]
        assert metrics["dead_letters"] == 3 and metrics["dead_letters_dropped"] == 5
    finally:
        pipeline.stop(grace=0.5)
    deleted_lines = [m for level, m in logger.lines if "oldest dead letters deleted" in m]
    assert len(deleted_lines) == 1 and deleted_lines[0].startswith("destination sink: oldest dead letters deleted")
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        assert [json.loads(d.payload)["n"] for d in buffer.list_dead_letters("sink")] == [5, 6, 7]
    finally:
        buffer.close()


def test_a_lowered_dead_letter_limit_applies_at_start(tmp_path: Path) -> None:
    pipeline = DeliveryPipeline(
        settings(tmp_path), {"sink": (Recorder(behaviour=reject_all), DestinationDeliveryParams())}, LOG
    )
    pipeline.start()
    try:
        for i in range(4):
            pipeline.submit("sink", record(i))
        wait_until(lambda: pipeline.metrics()["sink"]["dead_letters"] == 4, what="dead letters")
    finally:
        pipeline.stop(grace=0.5)
    lowered = DestinationDeliveryParams(dead_letter_limit_size="1")
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(), lowered)}, LOG)
    pipeline.start()
    try:
        metrics = pipeline.metrics()["sink"]
        assert metrics["dead_letters"] == 0 and metrics["dead_letters_dropped"] == 4
    finally:
        pipeline.stop(grace=0.5)


def test_partial_outcome_is_per_record(tmp_path: Path) -> None:
    def partial(call: int, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        if call == 1:
            # In a batch of 0..4: 1 must be retried, 3 is refused, the others are confirmed.
            return SendOutcome(retry={1: "timeout"}, reject={3: "schema mismatch"})
        return None

    sink = Recorder(behaviour=partial)
    pipeline = DeliveryPipeline(
        settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG, wait=RecordedWaits()
    )
    pipeline.start()
    try:
        for i in range(5):
            pipeline.submit("sink", record(i))
        pipeline.flush_intake(5)
        wait_until(lambda: pipeline.metrics()["sink"]["sent"] == 4, what="4 records confirmed")
        delivered = sorted(r.data["n"] for r in sink.delivered)
        assert delivered == [0, 1, 2, 4]
        metrics = pipeline.metrics()["sink"]
        assert metrics["dead_lettered"] == 1 and metrics["retried"] == 1 and metrics["buffered"] == 0
    finally:
        pipeline.stop(grace=0.5)


def test_retry_limit_dead_letters_after_the_last_retry(tmp_path: Path) -> None:
    def always_fail(call: int, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("connection refused")

    sink = Recorder(behaviour=always_fail)
    waits = RecordedWaits()
    pipeline = DeliveryPipeline(
        settings(tmp_path), {"sink": (sink, DestinationDeliveryParams(retry_limit=2))}, LOG, wait=waits
    )
    pipeline.start()
    try:
        pipeline.submit("sink", record(1))
        wait_until(lambda: pipeline.metrics()["sink"]["dead_lettered"] == 1, what="dead letter")
        assert sink.calls == 3  # the first attempt and two retries
        assert pipeline.metrics()["sink"]["retried"] == 2
    finally:
        pipeline.stop(grace=0.5)
    assert [d.attempts for d in _dead_letters(tmp_path)] == [3]


def test_an_outcome_listener_hears_of_dead_letters_only_once_they_are_committed(tmp_path: Path) -> None:
    """`dc ingest` acknowledges a record's message when its listener hears of it: a dead letter told
    before it is on disk was a record a crash left nowhere."""
    sent = [record(n) for n in range(4)]

    def mixed(call: int, batch: Sequence[OutgoingRecord]) -> SendOutcome:
        # 0 confirmed, 1 refused for good, 2 failing (retry_limit 1: dead after its second failure), 3 not ready.
        outcome = SendOutcome()
        for i, r in enumerate(batch):
            n = r.data["n"]
            if n == 1:
                outcome.reject[i] = "400 Bad Request"
            elif n == 2:
                outcome.retry[i] = "503"
            elif n == 3 and call == 1:
                outcome.waiting[i] = "its file is not uploaded yet"
        return outcome

    heard: list[tuple[str, bool, bool]] = []  # (record_id, dead_lettered, its dead letter on disk then)
    reader = SqliteBuffer(tmp_path / FILE_NAME)

    def listener(destination: str, record_ids: list[str], dead_lettered: bool) -> None:
        on_disk = {d.record_id for d in reader.list_dead_letters(destination)}
        heard.extend((rid, dead_lettered, rid in on_disk) for rid in record_ids)

    sink = Recorder(behaviour=mixed)
    pipeline = DeliveryPipeline(
        settings(tmp_path, scheduler_base=0.01, scheduler_cap=0.02),
        {"sink": (sink, DestinationDeliveryParams(retry_limit=1))},
        LOG,
    )
    pipeline.add_outcome_listener(listener)
    pipeline.start()
    try:
        for r in sent:
            pipeline.submit("sink", r)
        wait_until(lambda: len(heard) == 4, what="every outcome heard")
    finally:
        pipeline.stop(grace=0.5)
        reader.close()
    assert sorted(heard) == sorted(
        [
            (sent[0].record_id, False, False),
            (sent[1].record_id, True, True),
            (sent[2].record_id, True, True),
            (sent[3].record_id, False, False),
        ]
    )


def test_dc_buffer_list_counts_the_try_that_was_refused(tmp_path: Path) -> None:
    """A record refused at its first try was tried once: `dc buffer list` said "tries 0"."""
    from tests.test_buffer import _cli

    sink = Recorder(behaviour=reject_all)
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    try:
        pipeline.submit("sink", record(1))
        wait_until(lambda: pipeline.metrics()["sink"]["dead_lettered"] == 1, what="dead letter")
    finally:
        pipeline.stop(grace=0.5)
    assert [d.attempts for d in _dead_letters(tmp_path)] == [sink.calls] == [1]
    code, text = _cli(tmp_path, "list")
    header, row = text.splitlines()[:2]
    assert code == 0 and "tries" in header and row.split()[:4][3] == "1", text  # id, destination, failed at, tries


def _dead_letters(tmp_path: Path) -> list[Any]:
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        return buffer.list_dead_letters()
    finally:
        buffer.close()


def test_a_dead_destination_does_not_delay_another(tmp_path: Path) -> None:
    blocked = threading.Event()

    def hang(call: int, batch: Sequence[OutgoingRecord]) -> None:
        blocked.wait(10)
        raise RetryableError("timed out")

    dead = Recorder("dead", behaviour=hang)
    alive = Recorder("alive")
    pipeline = DeliveryPipeline(
        settings(tmp_path),
        {"dead": (dead, DestinationDeliveryParams()), "alive": (alive, DestinationDeliveryParams())},
        LOG,
    )
    pipeline.start()
    try:
        for i in range(200):
            r = record(i)
            pipeline.submit("dead", r)
            pipeline.submit("alive", r)
        assert len(alive.wait_for(200, timeout=5)) == 200
        assert pipeline.metrics()["dead"]["sent"] == 0
    finally:
        blocked.set()
        pipeline.stop(grace=0.5)


def test_stop_leaves_undelivered_records_for_the_next_pipeline(tmp_path: Path) -> None:
    def down(call: int, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("network unreachable")

    first = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(behaviour=down), DestinationDeliveryParams())}, LOG)
    first.start()
    sent = [record(i) for i in range(50)]
    for r in sent:
        first.submit("sink", r)
    first.stop(grace=0.2)

    sink = Recorder()
    second = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    second.start()
    try:
        got = sink.wait_for(50)
        assert [r.record_id for r in got] == [r.record_id for r in sent]
    finally:
        second.stop(grace=0.5)


class CountingRecorder(Recorder):
    """A destination with counters of its own, as a plugin keeps them (reconnections, say)."""

    def counters(self) -> dict[str, int]:
        return {"batches": self.calls}


def test_metrics_over_http(tmp_path: Path) -> None:
    sink = CountingRecorder()
    pipeline = DeliveryPipeline(
        settings(tmp_path, http_server=True, http_port=0), {"sink": (sink, DestinationDeliveryParams())}, LOG
    )
    pipeline.start()
    try:
        pipeline.submit("sink", record(1))
        sink.wait_for(1)
        wait_until(lambda: pipeline.metrics()["sink"]["sent"] == 1)
        address = pipeline.http_address
        assert address is not None and address[0] == "127.0.0.1"
        base = f"http://{address[0]}:{address[1]}/api/v1"
        with urllib.request.urlopen(f"{base}/health", timeout=5) as reply:
            assert json.load(reply) == {"status": "ok", "destinations": {"sink": {"state": "ok"}}}
        with urllib.request.urlopen(f"{base}/metrics", timeout=5) as reply:
            body = json.load(reply)
        assert body["destinations"]["sink"]["sent"] == 1
        assert body["destinations"]["sink"]["plugin"] == {"batches": 1}, "the plugin's own counters are served too"
        assert body["buffer"]["storage_sync"] == "normal"
        with urllib.request.urlopen(f"{base}/metrics/prometheus", timeout=5) as reply:
            text = reply.read().decode()
        assert 'dc_delivery_sent_total{destination="sink"} 1' in text
        assert 'dc_delivery_plugin_batches_total{destination="sink"} 1' in text
    finally:
        pipeline.stop(grace=0.5)
    assert pipeline.http_address is None


def test_records_submitted_after_stop_are_counted_as_dropped(tmp_path: Path) -> None:
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(), DestinationDeliveryParams())}, LOG)
    pipeline.start()
    pipeline.stop(grace=0.1)
    pipeline.submit("sink", record(1))
    assert pipeline.metrics()["sink"]["dropped"] == 1


@pytest.mark.parametrize("storage_sync", ["normal", "full"])
def test_flush_intake_means_committed(tmp_path: Path, storage_sync: str) -> None:
    def down(call: int, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("down")

    pipeline = DeliveryPipeline(
        settings(tmp_path, storage_sync=storage_sync),
        {"sink": (Recorder(behaviour=down), DestinationDeliveryParams())},
        LOG,
    )
    pipeline.start()
    try:
        for i in range(1000):
            pipeline.submit("sink", record(i))
        assert pipeline.flush_intake(10)
        other = SqliteBuffer(tmp_path / FILE_NAME)  # another connection sees the commit
        try:
            assert other.stats("sink").rows == 1000
        finally:
            other.close()
    finally:
        pipeline.stop(grace=0.1)


def test_size_limit_drops_the_oldest_counts_and_logs_once(tmp_path: Path) -> None:
    logger = RecordingLogger()

    def down(call: int, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("down")

    size = len(record(99).to_json().encode())  # the records 80..99 have the same size
    params = DestinationDeliveryParams(storage_total_limit_size=str(20 * size + 10), when_full="drop_oldest")
    pipeline = DeliveryPipeline(
        settings(tmp_path), {"sink": (Recorder(behaviour=down), params)}, logger, wait=RecordedWaits()
    )
    pipeline.start()
    try:
        for i in range(100):
            pipeline.submit("sink", record(i))
            if i % 10 == 9:
                pipeline.flush_intake(5)  # several group commits, so several drops in the burst
        # A commit during a send leaves the rows in it to the send's failure, which drops them then.
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 20, what="the limit applied")
        metrics = pipeline.metrics()["sink"]
        assert metrics["buffered"] == 20 and metrics["dropped"] == 80 and metrics["received"] == 100
    finally:
        pipeline.stop(grace=0.1)
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        assert [json.loads(r.payload)["n"] for r in buffer.read_batch("sink", 100)] == list(range(80, 100))
    finally:
        buffer.close()
    drops = [line for level, line in logger.lines if "records dropped" in line]
    assert 1 <= len(drops) <= 2, drops  # the burst's first line, and its summary at stop
    assert "storage_total_limit_size" in drops[0]


def test_a_corrupt_buffer_at_start_is_set_aside_and_new_records_flow(tmp_path: Path) -> None:
    (tmp_path / FILE_NAME).write_bytes(b"\x00garbage" * 4096)
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    try:
        pipeline.submit("sink", record(1))
        assert sink.wait_for(1)[0].data["n"] == 1
        assert pipeline.buffer_metrics()["quarantined"] == 1
        assert any(level == "error" and "moved aside" in line for level, line in logger.lines)
        assert len(list(tmp_path.glob(f"{FILE_NAME}.corrupt-*"))) == 1
    finally:
        pipeline.stop(grace=0.5)


def submit_padded(pipeline: DeliveryPipeline, total: int) -> list[str]:
    """Submit ``total`` records of ~200 bytes to destination "sink"; their ids in order."""
    sent_ids = []
    for i in range(total):
        rec = record(i)
        rec.data["pad"] = "x" * 120
        sent_ids.append(rec.record_id)
        pipeline.submit("sink", rec)
    return sent_ids


def test_live_damage_shows_in_health_and_the_next_start_salvages_it(tmp_path: Path) -> None:
    """5,000 records wait for a destination that is down; 10 pages of the file in use are damaged.

    The integrity check makes it visible (health 503, ``buffer_damaged``); the next start sets the
    file aside and puts back what is readable: delivered + lost_to_damage = sent, >= 95 % delivered.
    """
    total = 5000
    up = threading.Event()

    def down_until_up(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if not up.is_set():
            raise RetryableError("connection refused")

    logger = RecordingLogger()
    sink = Recorder(behaviour=down_until_up)
    # A long backoff: the sender does not read the file again while the test damages it.
    config = settings(tmp_path, http_server=True, http_port=0, scheduler_base=60.0, scheduler_cap=60.0)
    params = DestinationDeliveryParams(batch_size=500)
    pipeline = DeliveryPipeline(config, {"sink": (sink, params)}, logger)
    pipeline.start()
    try:
        sent_ids = submit_padded(pipeline, total)
        assert pipeline.flush_intake(10)
        wait_until(lambda: pipeline.metrics()["sink"]["retried"] >= 500, what="the first failed attempt recorded")
        assert pipeline.check_buffer() == "ok" and pipeline.healthy()
        with contextlib.closing(sqlite3.connect(tmp_path / FILE_NAME)) as other:  # what is committed, in the file
            other.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
        damage_pages(tmp_path / FILE_NAME)
        found = pipeline.check_buffer()
        assert found != "ok"
        address = pipeline.http_address
        assert address is not None
        base = f"http://{address[0]}:{address[1]}/api/v1"
        with pytest.raises(urllib.error.HTTPError) as health:
            urllib.request.urlopen(f"{base}/health", timeout=5)
        assert health.value.code == 503
        with urllib.request.urlopen(f"{base}/metrics", timeout=5) as reply:
            state = json.load(reply)["buffer"]
        assert state["buffer_damaged"] is True and state["last_check_result"] == found
        assert abs(state["last_check_time"] - time.time()) < 60
        with urllib.request.urlopen(f"{base}/metrics/prometheus", timeout=5) as reply:
            assert "dc_delivery_buffer_damaged 1" in reply.read().decode()
        assert [line for level, line in logger.lines if level == "error" and "is damaged" in line]
    finally:
        pipeline.stop(grace=0.1)

    up.set()
    pipeline = DeliveryPipeline(config, {"sink": (sink, params)}, logger)
    pipeline.start()
    try:
        # Salvaged beside delivery, not in start(): a large file takes its time.
        wait_until(lambda: pipeline.buffer_metrics()["quarantined"] == 1, 20, "the salvage done")
        metrics = pipeline.metrics()["sink"]
        lost = metrics["lost_to_damage"]
        assert metrics["salvaged"] + lost == total
        wait_until(lambda: len({r.record_id for r in sink.delivered}) + lost >= total, 30, "the salvaged records")
        delivered = {r.record_id for r in sink.delivered}
        assert delivered <= set(sent_ids)
        assert len(delivered) + lost == total, "delivered + counted = sent"
        assert len(delivered) >= 0.95 * total, f"{len(delivered)} of {total} delivered"
        buffer_state = pipeline.buffer_metrics()
        assert buffer_state["quarantined"] == 1 and buffer_state["buffer_damaged"] is False and pipeline.healthy()
        assert len([line for level, line in logger.lines if "moved aside" in line]) == 1
        said = [line for level, line in logger.lines if "salvaged from" in line]
        assert len(said) == 1 and f"lost to the damage {lost} (sink {lost})" in said[0], said
    finally:
        pipeline.stop(grace=0.5)


def test_damage_met_during_delivery_is_salvaged_at_once(tmp_path: Path) -> None:
    """A sender meets damaged pages mid-backlog: the file is set aside and salvaged while running, and
    every record is delivered or counted in lost_to_damage."""
    total = 5000
    first = threading.Event()
    go_on = threading.Event()

    def slow_at_first(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if call == 1:
            first.set()
            assert go_on.wait(10)

    logger = RecordingLogger()
    sink = Recorder(behaviour=slow_at_first)
    pipeline = DeliveryPipeline(
        settings(tmp_path, buffer_check_interval=0.0),
        {"sink": (sink, DestinationDeliveryParams(batch_size=500))},
        logger,
    )
    pipeline.start()
    try:
        sent_ids = submit_padded(pipeline, total)
        assert pipeline.flush_intake(10)
        assert first.wait(10)
        with contextlib.closing(sqlite3.connect(tmp_path / FILE_NAME)) as other:
            other.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
        damage_pages(tmp_path / FILE_NAME)
        go_on.set()
        wait_until(lambda: pipeline.buffer_metrics()["quarantined"] == 1, 20, "the damage met and set aside")
        lost = pipeline.metrics()["sink"]["lost_to_damage"]
        wait_until(lambda: len({r.record_id for r in sink.delivered}) + lost >= total, 30, "the rest delivered")
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, 10, "an empty queue")
        delivered = {r.record_id for r in sink.delivered}
        assert delivered <= set(sent_ids) and len(delivered) + lost >= total, "delivered + counted >= sent"
        # Records of the batches read before the damage was met (in flight, read ahead) that were on
        # a damaged page are delivered and counted too: the file no longer says which they were.
        assert len(delivered) + lost <= total + 2 * 500
        assert len(delivered) >= 0.95 * total
    finally:
        pipeline.stop(grace=0.5)


def test_a_salvage_cut_short_goes_on_at_the_next_start_without_copying_twice(tmp_path: Path) -> None:
    total = 5000
    path = tmp_path / FILE_NAME
    buffer = SqliteBuffer(path)
    payload = '{"pad":"' + "x" * 150 + '"}'
    buffer.append({"sink": [PendingRecord(f"id-{i}", "/t", i, payload) for i in range(total)]})
    buffer.close()
    damage_pages(path)
    buffer = SqliteBuffer(path, defer_salvage=True)
    if buffer.pending_salvage() is None:
        buffer.set_aside("integrity check", defer=True)
    answers = iter([False])  # stop after the second transaction, as a server stopping would
    with pytest.raises(SalvageStopped):
        buffer.salvage_pending(stop=lambda: next(answers, True))
    assert buffer.stats("sink").rows == 4000
    buffer.close()

    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    try:
        wait_until(lambda: pipeline.buffer_metrics()["quarantined"] == 1, 20, "the salvage finished")
        metrics = pipeline.metrics()["sink"]
        assert metrics["salvaged"] + metrics["lost_to_damage"] == total
        wait_until(lambda: len(sink.delivered) >= metrics["salvaged"], 20, "the salvaged records delivered")
        delivered = [r.record_id for r in sink.delivered]
        assert len(delivered) == len(set(delivered)) == metrics["salvaged"] >= 0.95 * total, "each once"
    finally:
        pipeline.stop(grace=0.5)
    assert any("going on with the salvage" in line for _, line in logger.lines)


def test_an_unwritable_storage_path_falls_back_to_the_default(tmp_path: Path, monkeypatch: Any) -> None:
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where a folder should be")
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(
        settings(tmp_path, storage_path=str(blocked / "buffer")),
        {"sink": (sink, DestinationDeliveryParams())},
        logger,
    )
    pipeline.start()
    try:
        pipeline.submit("sink", record(1))
        sink.wait_for(1)
        # The default folder of the root namespace in this domain (dc_destinations.storage).
        assert pipeline.storage_file == tmp_path / "data" / "dc" / "buffer" / "domain-7" / "default" / FILE_NAME
        assert any(level == "error" and "cannot be used" in line for level, line in logger.lines)
    finally:
        pipeline.stop(grace=0.5)


def test_stop_within_grace_delivers_what_it_can(tmp_path: Path) -> None:
    sink = Recorder()
    pipeline = DeliveryPipeline(
        settings(tmp_path, flush=30.0), {"sink": (sink, DestinationDeliveryParams(batch_size=1000))}, LOG
    )
    pipeline.start()
    for i in range(10):
        pipeline.submit("sink", record(i))
    pipeline.stop(grace=5.0)  # the flush timer is far away: stop itself must deliver
    assert len(sink.delivered) == 10


# -- kill -9 with real processes ---------------------------------------------------------------

_CHILD = r"""
import json, os, sys, time
from dc_core.destination import Destination, OutgoingRecord
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

class Log:
    def debug(self, m, **k): pass
    info = warning = error = debug

class AppendToFile(Destination):
    def send(self, batch):
        with open(sys.argv[2], "a") as out:
            for r in batch:
                out.write(r.to_json() + "\n")
        time.sleep(0.002)  # a slow destination keeps records in flight

count = int(sys.argv[3])
pipeline = DeliveryPipeline(
    DeliveryParams(storage_path=sys.argv[1], storage_sync=sys.argv[4], flush=0.01),
    {"file": (AppendToFile(None, None), DestinationDeliveryParams(batch_size=100))},
    Log(),
)
pipeline.start()
for n in range(count):
    rid = new_record_id()
    pipeline.submit("file", OutgoingRecord(rid, "/t", n, {"n": n, "record_id": rid}))
    if n % 250 == 249:
        pipeline.flush_intake()
        print(f"committed {n}", flush=True)
if count:
    pipeline.flush_intake()
    print(f"committed {count - 1}", flush=True)
while pipeline.metrics()["file"]["buffered"]:
    time.sleep(0.01)
print("drained", flush=True)
pipeline.stop(1.0)
"""


@pytest.mark.parametrize("storage_sync", ["normal", "full"])
def test_kill_9_loses_nothing_that_was_committed(tmp_path: Path, storage_sync: str) -> None:
    out = tmp_path / "out.jsonl"
    storage = tmp_path / "buffer"
    total = 10_000
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(storage), str(out), str(total), storage_sync],
        stdout=subprocess.PIPE,
        text=True,
    )
    committed = -1
    try:
        assert child.stdout is not None
        for line in child.stdout:
            committed = int(line.split()[1])
            if committed >= total // 2:
                child.send_signal(signal.SIGKILL)
                break
    finally:
        child.kill()
        child.wait()
    assert committed >= total // 2
    delivered_before = out.read_text().count("\n") if out.exists() else 0
    assert delivered_before < committed + 1, "the kill should catch records in flight"

    restart = subprocess.run(
        [sys.executable, "-c", _CHILD, str(storage), str(out), "0", storage_sync],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "drained" in restart.stdout, restart.stderr
    numbers = [json.loads(line)["n"] for line in out.read_text().splitlines()]
    missing = set(range(committed + 1)) - set(numbers)
    assert not missing, f"{len(missing)} committed records lost, e.g. {sorted(missing)[:5]}"
    duplicates = len(numbers) - len(set(numbers))
    print(
        f"storage_sync={storage_sync}: {committed + 1} committed before kill -9, "
        f"{len(set(numbers))} delivered, {duplicates} duplicates"
    )


def test_the_same_pipeline_can_start_again_after_stop(tmp_path: Path) -> None:
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (sink, DestinationDeliveryParams())}, LOG)
    pipeline.start()
    pipeline.submit("sink", record(1))
    sink.wait_for(1)
    pipeline.stop(grace=0.5)
    pipeline.start()  # deactivate, then activate again
    try:
        pipeline.submit("sink", record(2))
        assert [r.data["n"] for r in sink.wait_for(2)] == [1, 2]
        assert pipeline.metrics()["sink"]["received"] == 2
    finally:
        pipeline.stop(grace=0.5)


def test_commit_listeners_hear_every_committed_record(tmp_path: Path) -> None:
    heard: list[tuple[str, str]] = []
    pipeline = DeliveryPipeline(
        settings(tmp_path),
        {"a": (Recorder("a"), DestinationDeliveryParams()), "b": (Recorder("b"), DestinationDeliveryParams())},
        LOG,
    )
    pipeline.add_commit_listener(heard.extend)
    pipeline.start()
    try:
        sent = [record(i) for i in range(20)]
        for r in sent:
            pipeline.submit("a", r)
            pipeline.submit("b", r)
        assert pipeline.flush_intake(5)
        assert sorted(heard) == sorted([("a", r.record_id) for r in sent] + [("b", r.record_id) for r in sent])
    finally:
        pipeline.stop(grace=0.5)


def test_a_full_intake_queue_drops_and_counts(tmp_path: Path) -> None:
    logger = RecordingLogger()
    pipeline = DeliveryPipeline(
        settings(tmp_path, intake_queue_limit=5, commit_interval=0.5),
        {"sink": (Recorder(), DestinationDeliveryParams())},
        logger,
    )
    pipeline.start()
    try:
        for i in range(50):
            pipeline.submit("sink", record(i))
        assert pipeline.flush_intake(5)
        metrics = pipeline.metrics()["sink"]
        assert metrics["received"] == 50
        assert metrics["dropped"] >= 40
        assert sum("intake_queue_limit" in line for _level, line in logger.lines) == 1
    finally:
        pipeline.stop(grace=0.5)


def test_the_intake_queue_is_bounded_in_bytes_too_drops_counted(tmp_path: Path) -> None:
    """Few records but large ones (a flood of big camera records) are held to intake_queue_limit_bytes."""
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(
        settings(tmp_path, intake_queue_limit=1_000_000, intake_queue_limit_bytes="8K", commit_interval=0.5),
        {"sink": (sink, DestinationDeliveryParams())},
        logger,
    )
    pipeline.start()
    try:
        sent = [
            OutgoingRecord.serialised(rid, "/dc/measurement/camera", i, {"n": i, "frame": "x" * 1000})
            for i, rid in enumerate(new_record_id() for _ in range(100))
        ]
        kept = [pipeline.submit_record([("sink", r)]) for r in sent]
        # The writer waits commit_interval before its first commit: 8 records of ~1 KB fill the 8 KB.
        assert pipeline.buffer_metrics()["intake_pending_bytes"] <= 8 * 1024
        assert pipeline.flush_intake(5)
        assert pipeline.buffer_metrics()["intake_pending_bytes"] == 0
        delivered = sink.wait_for(sum(kept))
        metrics = pipeline.metrics()["sink"]
        assert metrics["received"] == len(sent)
        assert 0 < len(delivered) < len(sent) and metrics["dropped"] > 0
        assert len(delivered) + metrics["dropped"] == len(sent)
        assert {r.record_id for r in delivered} == {r.record_id for r, k in zip(sent, kept, strict=True) if k}
        assert sum("intake_queue_limit_bytes (8K)" in line for level, line in logger.lines if level == "error") == 1
    finally:
        pipeline.stop(grace=0.5)


def test_records_submitted_together_are_kept_or_dropped_together_and_committed_in_one_piece(tmp_path: Path) -> None:
    logger = RecordingLogger()
    pipeline = DeliveryPipeline(
        settings(tmp_path, intake_queue_limit=5, commit_interval=0.5),
        {"a": (Recorder(), DestinationDeliveryParams()), "b": (Recorder(), DestinationDeliveryParams())},
        logger,
    )
    heard: list[list[tuple[str, str]]] = []
    pipeline.add_commit_listener(lambda committed: heard.append(list(committed)))
    pipeline.start()
    try:
        first = [record(i) for i in range(4)]
        # Under the limit: taken whole, even though it leaves the limit behind (4 records, 8 copies).
        assert pipeline.submit_records([([("a", r), ("b", r)], ("/t", 100 + i, i + 1)) for i, r in enumerate(first)])
        # The limit (5 records waiting) counts records, not hand-offs: 4 wait, so 2 more are taken...
        assert pipeline.submit_records([([("a", record(4))], None), ([("a", record(5))], None)])
        # ...and then nothing, all of a submission dropped and counted.
        assert not pipeline.submit_records([([("a", record(6)), ("b", record(6))], None), ([("a", record(7))], None)])
        assert pipeline.flush_intake(5)
        committed = [pair for commit in heard for pair in commit]
        assert committed[:8] == [(name, r.record_id) for r in first for name in ("a", "b")]
        assert len(committed) == 10
        assert pipeline.metrics()["a"]["dropped"] == 2 and pipeline.metrics()["b"]["dropped"] == 1
        assert sum("intake_queue_limit" in line for _level, line in logger.lines) == 1
        assert pipeline.hop_keys() == [("/t", 100 + i, i + 1) for i in range(4)]
    finally:
        pipeline.stop(grace=0.5)


def test_a_copy_for_no_destination_here_is_said_and_the_writer_commits_the_rest(tmp_path: Path) -> None:
    # The writer looks destinations up: a caller's wrong name must not stop it, nor lose the other copies.
    logger = RecordingLogger()
    pipeline = DeliveryPipeline(settings(tmp_path), {"a": (Recorder(), DestinationDeliveryParams())}, logger)
    pipeline.start()
    try:
        stray, kept = record(1), record(2)
        assert pipeline.submit_records([([("nowhere", stray), ("a", stray)], ("/t", 7, 1)), ([("a", kept)], None)])
        assert pipeline.flush_intake(5)
        assert pipeline.metrics()["a"]["received"] == 2
        assert pipeline.hop_keys() == [("/t", 7, 1)]
        assert [line for level, line in logger.lines if "'nowhere'" in line and level == "error"] == [
            f"delivery intake: record {stray.record_id} submitted for 'nowhere', not a destination here"
        ]
    finally:
        pipeline.stop(grace=0.5)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real file system of 2 MB (tmpfs), so that the buffer meets a real ENOSPC."""
    with tmpfs(tmp_path / "disk", "2m") as disk:
        yield disk


def test_a_full_disk_under_the_buffer_keeps_records_in_memory_until_space_returns(small_disk: Path) -> None:
    logger = RecordingLogger()
    sink = Recorder()
    pipeline = DeliveryPipeline(settings(small_disk), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    try:
        pipeline.submit("sink", record(0))
        sink.wait_for(1)
        # Record 0 deleted from the buffer before the disk fills (a disk filling meanwhile is the next test).
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="record 0 out of the buffer")
        filler = small_disk / "filler"
        fill(filler)
        # ~300 KB of records: more than the buffer's WAL can take without growing.
        padded = [
            OutgoingRecord(r.record_id, r.topic, r.stamp_ns, {**r.data, "pad": "x" * 2000})
            for r in (record(n) for n in range(1, 151))
        ]
        for outgoing in padded:
            pipeline.submit("sink", outgoing)
        wait_until(lambda: any("group commit failed" in line for _, line in logger.lines), what="a failed commit")
        failure = next(line for _, line in logger.lines if "group commit failed" in line)
        assert "database or disk is full" in failure, failure
        assert len(sink.delivered) == 1, "a record reaches a destination only once committed"
        # A commit that keeps failing is visible where operators look, not only in the log.
        assert not pipeline.healthy()
        assert "database or disk is full" in pipeline.metrics()["sink"]["last_error"]
        assert pipeline.metrics()["sink"]["failed"] >= 1
        assert "database or disk is full" in pipeline.buffer_metrics()["commit_error"]

        filler.unlink()
        delivered = sink.wait_for(151, timeout=30)
        assert [r.data["n"] for r in delivered] == list(range(151))
        metrics = pipeline.metrics()["sink"]
        assert metrics["dropped"] == 0 and metrics["buffered"] == 0
        assert pipeline.healthy() and pipeline.buffer_metrics()["commit_error"] == ""
    finally:
        pipeline.stop(grace=1.0)


def test_a_disk_that_fills_while_a_batch_is_sent_does_not_stop_the_sender(small_disk: Path) -> None:
    filler = small_disk / "filler"

    def fill_the_disk_first(call: int, batch: Sequence[OutgoingRecord]) -> None:
        if call == 1:
            fill(filler)  # the batch is confirmed, but deleting it from the buffer needs space

    logger = RecordingLogger()
    sink = Recorder(behaviour=fill_the_disk_first)
    pipeline = DeliveryPipeline(settings(small_disk), {"sink": (sink, DestinationDeliveryParams())}, logger)
    pipeline.start()
    try:
        pipeline.submit("sink", record(0))
        wait_until(
            lambda: any("updating the buffer" in line for _, line in logger.lines), what="the failed delete logged"
        )
        assert "database or disk is full" in pipeline.metrics()["sink"]["last_error"]
        filler.unlink()
        pipeline.submit("sink", record(1))
        wait_until(lambda: any(r.data["n"] == 1 for r in sink.delivered), what="record 1 delivered")
        # Record 0 again, once or more (the buffer could not forget it while the disk was full: how often
        # depends on the retries' timing), then record 1: at least once, in order, nothing lost.
        numbers = [r.data["n"] for r in sink.delivered]
        assert numbers[-1] == 1 and len(numbers) >= 3 and set(numbers[:-1]) == {0}, numbers
        wait_until(lambda: pipeline.metrics()["sink"]["buffered"] == 0, what="an empty queue")
    finally:
        pipeline.stop(grace=1.0)


# -- one owner per buffer ----------------------------------------------------------------------------


def test_a_second_pipeline_on_the_same_buffer_is_refused_until_the_first_lets_go(tmp_path: Path) -> None:
    first = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(), DestinationDeliveryParams())}, LOG)
    second = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(), DestinationDeliveryParams())}, LOG)
    first.claim_storage()
    try:
        with pytest.raises(BufferInUse) as refused:
            second.claim_storage()
        message = str(refused.value)
        assert f"the delivery buffer {tmp_path / FILE_NAME} is in use by process {os.getpid()}" in message
        assert "destination_server.ros__parameters.flb.storage_path" in message
    finally:
        first.release_storage()
    assert second.claim_storage() == tmp_path / FILE_NAME
    second.release_storage()


_HOLDER = r"""
import sys, time
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.settings import DeliveryParams
pipeline = DeliveryPipeline(DeliveryParams(storage_path=sys.argv[1]), {}, None)
pipeline.claim_storage()
print("claimed", flush=True)
time.sleep(600)
"""


def test_a_buffer_whose_owner_was_killed_is_taken_over_at_once(tmp_path: Path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "claimed"
        pipeline = DeliveryPipeline(settings(tmp_path), {"sink": (Recorder(), DestinationDeliveryParams())}, LOG)
        with pytest.raises(BufferInUse, match=f"in use by process {holder.pid}"):
            pipeline.claim_storage()
        holder.kill()  # kill -9: no cleanup runs in the holder
        holder.wait()
        assert (tmp_path / f"{FILE_NAME}.lock").exists(), "the lock file stays behind, stale"
        assert pipeline.claim_storage() == tmp_path / FILE_NAME
        pipeline.release_storage()
    finally:
        holder.kill()
        holder.wait()


def test_the_default_buffer_is_separated_by_ros_domain_and_namespace(tmp_path: Path, monkeypatch: Any) -> None:
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    base = tmp_path / "dc" / "buffer"
    assert default_storage_dir() == base / "domain-42" / "default"
    assert default_storage_dir("/robot1") == base / "domain-42" / "ns.robot1"
    assert default_storage_dir("/fleet/robot1/", "3") == base / "domain-3" / "ns.fleet.robot1"
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert default_storage_dir() == base / "domain-0" / "default"


def test_records_left_in_the_buffer_of_an_earlier_dc_are_mentioned_once_at_start(
    tmp_path: Path, monkeypatch: Any
) -> None:
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    legacy = tmp_path / "dc" / "buffer" / FILE_NAME
    old = SqliteBuffer(legacy)
    old.append({"out": [PendingRecord("r1", "/t", 1, '{"n":1}'), PendingRecord("r2", "/t", 2, '{"n":2}')]})
    old.close()
    logger = RecordingLogger()
    pipeline = DeliveryPipeline(DeliveryParams(), {"out": (Recorder("out"), DestinationDeliveryParams())}, logger)
    pipeline.claim_storage()
    pipeline.release_storage()
    (warning,) = logger.at("warning")
    assert f"2 records of an earlier DC wait in {legacy}" in warning
    assert f'flb.storage_path: "{legacy.parent}"' in warning
