"""Hand-off marks: where each publisher got to survives its process, and destination_server counts its end once.

The processes themselves (kill -9 in both modes) are in tests/test_fault_matrix.py::test_kill_9_of_a_server_holding_its_own_records.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from types import SimpleNamespace

import pytest

import dc_core.handoff_marks as marks
from dc_core.handoff import ENDED_SUFFIX, AckTracker, HandoffParams, HandoffSender, ack_document, forwarding
from dc_core.handoff_marks import HEADER, Ended, EndedWriters, WriterMark, ended_document, parse_ended
from dc_destinations.hop import HopIntake, HopKey
from tests.test_handoff import _Node, _Publisher

TOPIC = "/dc/measurement/ticks"


def read_mark(path: Path) -> tuple[int, int, bool, str]:
    data = path.read_bytes()
    _, high, acked, forwards = HEADER.unpack_from(data)
    return high, acked, bool(forwards), data[HEADER.size :].decode()


def ack(sender: HandoffSender, writer: int, floor: int, topic: str = TOPIC) -> None:
    sender._on_ack(SimpleNamespace(data=ack_document("destination-1", [(topic, writer, floor)])))


def test_a_publisher_s_mark_says_how_far_it_got_and_survives_it_while_records_are_held(tmp_path: Path) -> None:
    sender = HandoffSender(_Node(), HandoffParams(), [TOPIC], marks=tmp_path)
    publish = sender.output(TOPIC, _Publisher())
    (path,) = tmp_path.glob("*.mark")
    writer = int(path.name.removesuffix(".mark"), 16)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    for n in range(5):
        publish(1 + n, f'{{"n": {n}}}', "")
        assert read_mark(path) == (n + 1, 0, False, TOPIC), "written with each record"
    ack(sender, writer, 3)
    assert read_mark(path)[:2] == (5, 3)
    # Alive: its lock keeps it from being taken for an ended publisher.
    assert EndedWriters(tmp_path, print).scan() == []
    sender.close()
    assert path.exists(), "2 records held: the next start announces them"
    taken = EndedWriters(tmp_path, print)
    assert taken.scan() == [Ended(TOPIC, writer, 5, 3)]
    assert EndedWriters(tmp_path, print).scan() == [], "taken by one starting server only"
    taken.release()
    assert EndedWriters(tmp_path, print).scan() == [Ended(TOPIC, writer, 5, 3)], "released: announced again"


def test_a_publisher_that_ends_with_everything_acknowledged_leaves_nothing(tmp_path: Path) -> None:
    sender = HandoffSender(_Node(), HandoffParams(), [TOPIC], marks=tmp_path)
    publish = sender.output(TOPIC, _Publisher())
    (path,) = tmp_path.glob("*.mark")
    publish(1, "{}", "")
    ack(sender, int(path.name.removesuffix(".mark"), 16), 1)
    sender.close()
    assert list(tmp_path.iterdir()) == []


def test_what_has_nothing_to_announce_is_deleted_and_the_oldest_beyond_the_limit_are_forgotten_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def ended_mark(writer: int, high: int, acked: int, forwards: bool = False) -> Path:
        mark = WriterMark(tmp_path, writer, TOPIC)
        marks.NUMBER.pack_into(mark.map, marks.HIGH_AT, high)
        mark.acked(acked)
        if forwards:
            mark.forwards()
        mark.close(keep=True)
        return mark.path

    all_acknowledged = ended_mark(1, 10, 10)
    forwarding_source = ended_mark(2, 10, 4, forwards=True)  # counted from the source's numbers instead
    (tmp_path / "3.mark").write_bytes(b"not a mark")
    (tmp_path / "7.mark.new").write_bytes(b"")  # its process died making it
    (tmp_path / "other.txt").write_text("left alone")
    for writer in (4, 5, 6):
        path = ended_mark(writer, 10 + writer, 1)
        os.utime(path, (writer, writer))
    monkeypatch.setattr(marks, "MAX_ENDED", 2)
    warnings: list[str] = []
    ended = EndedWriters(tmp_path, warnings.append)
    assert sorted(e.writer for e in ended.scan()) == [5, 6]
    assert not all_acknowledged.exists() and not forwarding_source.exists() and not (tmp_path / "3.mark").exists()
    assert (tmp_path / "other.txt").exists() and not (tmp_path / "4.mark").exists()
    assert not (tmp_path / "7.mark.new").exists()
    assert any("publisher 4 ended holding up to 13 records" in w and "forgotten uncounted" in w for w in warnings)
    assert any("not a hand-off mark" in w for w in warnings)
    # destination_server acknowledged 5 to its end (15), 6 not yet (16).
    assert ended.retire({(TOPIC, 5): 15, (TOPIC, 6): 15}) == [Ended(TOPIC, 5, 15, 1)]
    assert not (tmp_path / "5.mark").exists() and (tmp_path / "6.mark").exists()
    assert parse_ended(ended_document("measurement_server", ended.ended())) == (
        "measurement_server",
        [Ended(TOPIC, 6, 16, 1)],
    )
    ended.release()


def test_a_forwarding_publisher_s_mark_says_so_before_its_first_record_leaves(tmp_path: Path) -> None:
    sender = HandoffSender(_Node(), HandoffParams(), [TOPIC], marks=tmp_path)
    publish = sender.output(TOPIC, _Publisher())
    forwarding(41)
    try:
        publish(1, "{}", "")
    finally:
        forwarding(0)
    (path,) = tmp_path.glob("*.mark")
    assert read_mark(path)[:3] == (1, 0, True)
    sender.close()


def test_an_announcement_that_does_not_parse_is_ignored() -> None:
    for text in ("", "[]", '{"ended": 3}', '{"server": "m", "ended": [["t", "zz", 1, 0]]}', '{"ended": []}'):
        assert parse_ended(text) is None, text
    assert parse_ended('{"server": "m", "ended": [["t", "0", 1, 0], ["t", "a", 5, 2]]}') == (
        "m",
        [Ended("t", 10, 5, 2)],
    )


def test_destination_server_counts_what_an_ended_publisher_never_delivered_once_even_across_its_restart() -> None:
    hop = HopIntake(window=100)
    writer = 7
    for seq in (1, 2, 3, 5, 6):  # 4 is on its way, 7..10 never left
        hop.check(TOPIC, HopKey(TOPIC, -writer, seq), low=1)
        hop.handled(HopKey(TOPIC, -writer, seq))
    assert hop.writer_ended(TOPIC, writer, high=10, acked=3) == (4, 5)
    stats = hop.stats()[TOPIC]
    assert (stats["missing"], stats["gaps"], stats["writers_ended"]) == (5, 1, 1)
    assert hop.writer_ended(TOPIC, writer, high=10, acked=3) is None, "announced again: counted once"
    # 4 arrives late after all (it was on its way): delivered, and taken off the count.
    verdict = hop.check(TOPIC, HopKey(TOPIC, -writer, 4), low=1)
    assert not verdict.duplicate and hop.stats()[TOPIC]["missing"] == 4

    # destination_server restarts: the buffer's keys, with the one saying the end was counted.
    restarted = HopIntake(window=100)
    restarted.load(
        [*(HopKey(TOPIC, -writer, s) for s in (1, 2, 3, 4, 5, 6)), HopKey(TOPIC + ENDED_SUFFIX, -writer, 10)]
    )
    assert restarted.writer_ended(TOPIC, writer, high=10, acked=3) is None
    assert restarted.stats().get(TOPIC, {}).get("missing", 0) == 0


def test_a_publisher_destination_server_does_not_know_lost_everything_after_its_acknowledged_number() -> None:
    hop = HopIntake(window=100)
    assert hop.writer_ended(TOPIC, 9, high=50, acked=20) == (21, 30)
    assert hop.stats()[TOPIC]["missing"] == 30


def test_the_commit_of_an_ended_publisher_acknowledges_it_to_its_end() -> None:
    tracker = AckTracker()
    assert tracker.committed([(TOPIC + ENDED_SUFFIX, -9, 50)])
    assert tracker.acks() == [(TOPIC, 9, 50)]
