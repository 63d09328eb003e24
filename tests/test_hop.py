"""The hop into destination_server: replays recognised, losses counted, keys kept with the records.

Pure tests of dc_destinations.hop, then the buffer and the delivery pipeline with the hop keys
(no ROS). The same behaviour with real processes: tests/test_e2e_delivery_restart.py.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.cli import _print_delivery
from dc_core.destination import Destination, OutgoingRecord
from dc_core.sequence_numbers import TopicWriters
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.buffer import FILE_NAME, PendingRecord, SqliteBuffer
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.hop import HopIntake, HopKey, HopLosses, hop_key
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.test_buffer import _cli

TOPIC = "/dc/measurement/numbers"


def key(seq: int, topic: str = TOPIC, source_ns: int | None = None) -> HopKey:
    return HopKey(topic, source_ns if source_ns is not None else 1_700_000_000_000_000_000 + seq, seq)


# -- keys from rclpy's MessageInfo -----------------------------------------------------------------


def test_the_key_is_topic_source_timestamp_and_sequence_number() -> None:
    info = {
        "source_timestamp": 1_795_328_208_936_538_330,
        "received_timestamp": 1_795_328_211_324_410_255,
        "publication_sequence_number": 501,
        "reception_sequence_number": None,
    }
    assert hop_key(TOPIC, info) == HopKey(TOPIC, 1_795_328_208_936_538_330, 501)


@pytest.mark.parametrize(
    "info",
    [
        None,
        {},
        {"source_timestamp": 0, "publication_sequence_number": 5},
        {"source_timestamp": 123, "publication_sequence_number": None},
        {"source_timestamp": 123, "publication_sequence_number": 0},
    ],
    ids=["no-info", "empty", "no-timestamp", "no-sequence", "zero-sequence"],
)
def test_without_timestamp_or_sequence_number_there_is_no_key(info: dict[str, Any] | None) -> None:
    # Records without a key could not be told apart: they are never dropped as duplicates.
    assert hop_key(TOPIC, info) is None


# -- writers and gaps ---------------------------------------------------------------------------------


def observe_all(writers: TopicWriters, seqs: Sequence[int]) -> list[int | None]:
    return [writers.observe(s) for s in seqs]


@pytest.mark.parametrize(
    ("seqs", "expected"),
    [
        ([1, 2, 3, 4], [None, 0, 0, 0]),
        ([1, 2, 6, 7], [None, 0, 3, 0]),
        # A publisher that restarted numbers from 1 again: a new writer, not a loss.
        ([1, 2, 3, 1, 2], [None, 0, 0, None, 0]),
        # Two publishers of one topic, interleaved, none lost.
        ([100, 1, 101, 2, 102, 3], [None, None, 0, 0, 0, 0]),
        # The same, and one record of the second is lost.
        ([100, 1, 101, 2, 102, 4], [None, None, 0, 0, 0, 1]),
        # Two publishers whose numbers are close, in step.
        ([99, 97, 98, 100, 99, 101], [None, None, 0, 0, 0, 0]),
    ],
    ids=["in-order", "jump", "restarted-publisher", "two-writers", "two-writers-one-lost", "close-numbers"],
)
def test_writers_are_told_apart_by_their_sequence_numbers(seqs: list[int], expected: list[int | None]) -> None:
    assert observe_all(TopicWriters(), seqs) == expected


def test_the_writer_heard_from_least_recently_is_forgotten_beyond_the_limit() -> None:
    writers = TopicWriters(max_writers=2)
    observe_all(writers, [50, 10])  # two writers
    writers.observe(11)
    writers.observe(1)  # a third one: the writer at 50 is forgotten
    assert writers.count == 2
    assert writers.observe(51) == 39, "51 now continues the writer at 11"


# -- the intake -------------------------------------------------------------------------------------


def test_a_handled_record_arriving_again_is_a_duplicate() -> None:
    hop = HopIntake(window=10)
    first = hop.check(TOPIC, key(1))
    assert not first.duplicate and first.new_writer
    hop.handled(key(1))
    assert hop.check(TOPIC, key(1)).duplicate
    assert hop.stats()[TOPIC] == {
        "received": 2,
        "duplicates": 1,
        "missing": 0,
        "gaps": 0,
        "writers": 1,
        "unkeyed": 0,
        "writers_ended": 0,
        "missing_lifetime": 0,
        "gaps_lifetime": 0,
    }


def test_a_record_not_handed_over_is_delivered_when_it_comes_again() -> None:
    # E.g. dropped because the intake queue was full: its replay must not be thrown away.
    hop = HopIntake(window=10)
    hop.check(TOPIC, key(1))
    assert not hop.check(TOPIC, key(1)).duplicate


def test_same_sequence_number_from_another_writer_or_topic_is_not_a_duplicate() -> None:
    hop = HopIntake(window=10)
    hop.check(TOPIC, key(1))
    hop.handled(key(1))
    assert not hop.check(TOPIC, key(1, source_ns=5)).duplicate
    assert not hop.check("/other", key(1, topic="/other")).duplicate


def test_skipped_sequence_numbers_are_counted_as_missing() -> None:
    hop = HopIntake(window=100)
    for seq in (1, 2, 3, 10, 11, 20):
        verdict = hop.check(TOPIC, key(seq))
        hop.handled(key(seq))
    assert verdict.skipped == 8 and verdict.first_skipped == 12
    stats = hop.stats()[TOPIC]
    assert stats["missing"] == 6 + 8 and stats["gaps"] == 2


def test_only_the_newest_keys_of_a_topic_are_kept() -> None:
    hop = HopIntake(window=3)
    for seq in range(1, 5):
        hop.check(TOPIC, key(seq))
        hop.handled(key(seq))
    assert not hop.check(TOPIC, key(1)).duplicate, "beyond the window: delivered again (a duplicate, not a loss)"
    assert all(hop.check(TOPIC, key(seq)).duplicate for seq in (2, 3, 4))


def test_records_without_key_are_counted_and_always_delivered() -> None:
    hop = HopIntake(window=10)
    assert not hop.check(TOPIC, None).duplicate
    hop.handled(None)
    assert not hop.check(TOPIC, None).duplicate
    assert hop.stats()[TOPIC]["unkeyed"] == 2


def test_after_a_restart_the_replayed_history_is_recognised_and_a_loss_beyond_it_counted() -> None:
    # The previous run buffered records 1..1500; the publisher went on to 4000 meanwhile and
    # replays its last 1,000 (3001..4000): 1501..3000 were published while nobody listened.
    kept = [key(seq) for seq in range(1, 1501)]
    hop = HopIntake(window=4000)
    hop.load(kept)
    verdicts = [hop.check(TOPIC, key(seq)) for seq in range(3001, 4001)]
    assert verdicts[0].skipped == 1500 and verdicts[0].first_skipped == 1501
    assert sum(v.skipped for v in verdicts) == 1500
    assert hop.stats()[TOPIC]["writers"] == 0, "the publisher is the one the previous run knew"


def test_after_a_short_restart_the_replay_overlaps_what_was_buffered() -> None:
    hop = HopIntake(window=4000)
    hop.load(key(seq) for seq in range(1, 1501))
    verdicts = [hop.check(TOPIC, key(seq)) for seq in range(801, 1801)]
    assert sum(v.duplicate for v in verdicts) == 700
    assert sum(v.skipped for v in verdicts) == 0
    assert hop.stats()[TOPIC]["missing"] == 0


# -- keys in the buffer -------------------------------------------------------------------------------


def pending(n: int) -> PendingRecord:
    return PendingRecord(new_record_id(), TOPIC, n, f'{{"n": {n}}}')


def test_keys_are_kept_oldest_first_and_survive_reopening(tmp_path: Path) -> None:
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    buffer.append({"file": [pending(1)]}, seen=[key(1)])
    buffer.append({}, seen=[key(2), key(1, topic="/other")])
    buffer.close()
    reopened = SqliteBuffer(tmp_path / FILE_NAME)
    assert reopened.seen_keys() == [key(1), key(2), key(1, topic="/other")]
    reopened.close()


def test_each_topic_keeps_about_its_newest_window_of_keys(tmp_path: Path) -> None:
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    buffer.append({}, seen=[key(1, topic="/other")])
    for seq in range(1, 201):
        buffer.append({}, seen=[key(seq)], seen_window=40)
    kept = [k.seq for k in map(HopKey._make, buffer.seen_keys()) if k.topic == TOPIC]
    assert 40 <= len(kept) <= 50
    assert kept == list(range(201 - len(kept), 201)), "the newest ones"
    assert HopKey("/other", key(1).source_ns, 1) in map(HopKey._make, buffer.seen_keys())
    buffer.close()


def test_keys_are_written_only_with_their_records(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    buffer = SqliteBuffer(tmp_path / FILE_NAME)

    def fail(*args: Any, **kwargs: Any) -> Any:
        raise sqlite3.OperationalError("database or disk is full")

    from dc_destinations.buffer import QueueLimit

    monkeypatch.setattr(buffer, "_apply_limit", fail)
    with pytest.raises(sqlite3.OperationalError):
        buffer.append({"file": [pending(1)]}, {"file": QueueLimit(1000, True)}, seen=[key(1)])
    assert buffer.seen_keys() == [], "a failed commit leaves no key behind"
    assert buffer.stats("file").rows == 0
    buffer.close()


# -- keys through the delivery pipeline -------------------------------------------------------------


class _Down(Destination[None]):
    """Never confirms: what was committed stays in the queue, where the test can count it."""

    def __init__(self, name: str) -> None:
        super().__init__(FakeContext(name=name), None)

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        raise ConnectionError("down")


def pipeline(tmp_path: Path) -> DeliveryPipeline:
    settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=60.0, scheduler_cap=60.0)
    destinations = {name: (_Down(name), DestinationDeliveryParams()) for name in ("a", "b")}
    return DeliveryPipeline(settings, destinations, RecordingLogger(), seen_window=100)


def outgoing(n: int) -> OutgoingRecord:
    return OutgoingRecord(new_record_id(), TOPIC, n, {"n": n})


def test_a_record_and_its_key_are_committed_together_for_every_destination(tmp_path: Path) -> None:
    delivery = pipeline(tmp_path)
    delivery.start()
    try:
        record = outgoing(1)
        assert delivery.submit_record([("a", record), ("b", record)], key(1))
        assert delivery.submit_record([], key(2)), "a record that reaches no destination: its key alone"
        assert delivery.flush_intake(10)
        assert delivery.hop_keys() == [key(1), key(2)]
        metrics = delivery.metrics()
        assert metrics["a"]["received"] == 1 and metrics["b"]["received"] == 1
    finally:
        delivery.stop(0.1)
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    assert buffer.stats("a").rows == 1 and buffer.stats("b").rows == 1
    buffer.close()


def test_a_record_the_pipeline_cannot_take_leaves_no_key(tmp_path: Path) -> None:
    delivery = pipeline(tmp_path)
    assert not delivery.submit_record([("a", outgoing(1))], key(1)), "not started"
    assert delivery.metrics()["a"]["dropped"] == 1
    delivery.start()
    try:
        assert delivery.flush_intake(10)
        assert delivery.hop_keys() == []
    finally:
        delivery.stop(0.1)


# -- losses counted, kept in the buffer beyond the run that counted them ------------------------------


def test_a_run_s_losses_go_into_the_buffer_with_its_records_and_the_next_run_starts_from_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A destination_server killed after it counted a loss took its counters with it: the buffer keeps
    the count, committed with the records that came after the gap, and the next run adds to it."""
    hop = HopIntake(window=100)
    delivery = pipeline(tmp_path)
    delivery.start()
    try:
        for seq in (1, 2, 6, 7):  # 3..5 never arrived
            verdict = hop.check(TOPIC, key(seq))
            assert not verdict.duplicate
            losses = hop.losses_not_handed_over()
            assert delivery.submit_records([([("a", outgoing(seq))], key(seq)), *(([], one) for one in losses)])
            hop.losses_handed_over(losses)
        assert hop.losses_not_handed_over() == [], "each loss handed over once"
        assert delivery.flush_intake(10)
        assert delivery.hop_loss_totals() == {TOPIC: (3, 1)}
    finally:
        delivery.stop(0.1)  # or a kill -9: what was committed stays
    # The next run: its own counters start at 0, the lifetime ones at the buffer's totals.
    again = pipeline(tmp_path)
    again.start()
    try:
        second = HopIntake(window=100)
        second.load(HopKey(*k) for k in again.hop_keys())
        second.load_loss_totals(again.hop_loss_totals())
        assert second.stats()[TOPIC]["missing"] == 0 and second.stats()[TOPIC]["missing_lifetime"] == 3
        second.check(TOPIC, key(10))  # 8 and 9
        losses = second.losses_not_handed_over()
        assert losses == [HopLosses(TOPIC, 2, 1)]
        assert again.submit_records([([], one) for one in losses])
        second.losses_handed_over(losses)
        assert again.flush_intake(10)
        assert again.hop_loss_totals() == {TOPIC: (5, 2)}
        assert second.stats()[TOPIC]["missing_lifetime"] == 5 and second.stats()[TOPIC]["gaps_lifetime"] == 2
    finally:
        again.stop(0.1)
    _print_delivery({"hop": second.stats()}, wide=False)  # what `dc status` prints of it
    assert (
        f"lost before destination_server: 2 on {TOPIC} (missing, 1 gaps); 3 more counted by earlier runs on this buffer"
        in capsys.readouterr().out
    )


def test_a_loss_taken_back_and_a_failed_commit_keep_the_totals_right(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    buffer.append({}, hop_losses=[HopLosses(TOPIC, 4, 1), HopLosses("/other", 1, 1)])
    buffer.append({}, hop_losses=[HopLosses(TOPIC, -1, 0)])  # one of them arrived after all

    def fail(*args: Any, **kwargs: Any) -> Any:
        raise sqlite3.OperationalError("database or disk is full")

    from dc_destinations.buffer import QueueLimit

    monkeypatch.setattr(buffer, "_apply_limit", fail)
    with pytest.raises(sqlite3.OperationalError):
        buffer.append({"file": [pending(1)]}, {"file": QueueLimit(1000, True)}, hop_losses=[HopLosses(TOPIC, 7, 1)])
    buffer.close()
    reopened = SqliteBuffer(tmp_path / FILE_NAME)
    assert reopened.hop_loss_totals() == {TOPIC: (3, 1), "/other": (1, 1)}, "the failed commit added nothing"
    reopened.close()
    code, text = _cli(tmp_path, "stats")  # `dc buffer stats`, with no server running
    assert code == 0
    assert f"lost before destination_server, all runs: 3 on {TOPIC} (1 gaps)" in text
    assert "lost before destination_server, all runs: 1 on /other (1 gaps)" in text
