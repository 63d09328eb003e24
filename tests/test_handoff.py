"""The hand-off's pure parts: what a publisher keeps, what destination_server acknowledges and counts."""

from __future__ import annotations

from dc_core.handoff import (
    MAX_ACK_WRITERS,
    SETTLED_SUFFIX,
    AckTracker,
    HandoffParams,
    HandoffSender,
    Unacked,
    ack_document,
    destination_inputs,
    forwarding,
    frame_key,
    parse_ack,
    parse_frame_key,
)
from dc_destinations.hop import HopIntake, HopKey, keyed_hop_key, source_key

TOPIC = "/dc/measurement/numbers"


def test_a_frame_key_reads_back_and_anything_else_is_no_key() -> None:
    assert parse_frame_key(frame_key(0xABC, 7, 3)) == (0xABC, 7, 3, 0)
    assert parse_frame_key(frame_key(0xABC, 7, 3, 99)) == (0xABC, 7, 3, 99)
    for other in ("", "map", "dc:", "dc:zz:1:1", "dc:1:2", "dc:1:2:3", "dc:1:0:0", "dc:1:5:1:-1"):
        assert parse_frame_key(other) is None, other


def test_the_publisher_keeps_records_until_acknowledged_and_drops_the_oldest_beyond_its_limits() -> None:
    unacked = Unacked(limit_records=3, limit_bytes=0)
    for n in range(1, 6):
        seq, _ = unacked.take_number()
        assert seq == n
        unacked.keep(seq, b"x" * 10, now=float(n))
    assert len(unacked) == 3 and unacked.dropped == 2 and unacked.low == 3
    assert unacked.ack(3) == 1 and unacked.low == 4 and unacked.bytes == 20
    assert unacked.ack(2) == 0, "an older ack changes nothing"
    by_bytes = Unacked(limit_records=100, limit_bytes=25)
    for _ in range(3):
        seq, _ = by_bytes.take_number()
        by_bytes.keep(seq, b"y" * 10, now=0.0)
    assert len(by_bytes) == 2 and by_bytes.dropped == 1


def test_records_not_acknowledged_are_due_again_in_slices_oldest_first() -> None:
    unacked = Unacked(limit_records=100, limit_bytes=0)
    for n in range(1, 11):
        seq, _ = unacked.take_number()
        unacked.keep(seq, bytes([n]), now=float(n))
    assert unacked.due(sent_before=5.0, now=20.0, limit=3) == [b"\x01", b"\x02", b"\x03"]
    assert unacked.due(sent_before=5.0, now=20.0, limit=3) == [b"\x04", b"\x05"]
    assert unacked.due(sent_before=5.0, now=21.0, limit=3) == []
    assert unacked.resent == 5


def test_acks_are_cumulative_from_the_publishers_oldest_record_and_only_of_committed_records() -> None:
    tracker = AckTracker()
    writer = 0x1234
    tracker.committed([(TOPIC, -writer, 5), (TOPIC, -writer, 6)])
    assert tracker.acks() == [], "where the publisher's records start is not known yet"
    tracker.saw(TOPIC, writer, 5)
    assert tracker.acks() == [(TOPIC, writer, 6)]
    assert tracker.committed([(TOPIC, -writer, 8)]) is False, "7 is not committed: no progress"
    assert tracker.committed([(TOPIC, -writer, 7)]) is True
    assert tracker.acks() == [(TOPIC, writer, 8)]
    # Positions of the source and DDS-keyed records are no publisher's acks.
    tracker.committed([(TOPIC + " <- source", -writer, 100), (TOPIC, 1_700_000_000, 9)])
    assert tracker.acks() == [(TOPIC, writer, 8)]
    assert parse_ack(ack_document("abc", tracker.acks())) == {"instance": "abc", "acks": {(TOPIC, writer): 8}}
    assert parse_ack("not json") is None and parse_ack('{"instance": "x"}') is None


def test_the_hop_drops_a_record_sent_again_and_counts_only_what_the_publisher_dropped_unacknowledged() -> None:
    hop = HopIntake(window=100)

    def receive(seq: int, low: int) -> tuple[bool, int]:
        keyed = keyed_hop_key(TOPIC, frame_key(7, seq, low))
        assert keyed is not None
        verdict = hop.check(TOPIC, keyed[0], keyed[1])
        if not verdict.duplicate:
            hop.handled(keyed[0])
        return verdict.duplicate, verdict.skipped

    assert receive(1, 1) == (False, 0)
    assert receive(2, 1) == (False, 0)
    assert receive(5, 1) == (False, 0), "3 and 4 may still come: sent again"
    assert receive(2, 1) == (True, 0), "sent again after a restart: dropped"
    assert receive(3, 1) == (False, 0)
    # The publisher dropped 4 at its limit: its oldest held is now 6.
    assert receive(6, 6) == (False, 1)
    assert hop.stats()[TOPIC]["missing"] == 1
    # 4 was on its way when the publisher dropped it: it arrives, and is no longer counted as lost.
    assert receive(4, 1) == (False, 0)
    assert receive(4, 1) == (True, 0)
    assert hop.stats()[TOPIC]["missing"] == 0
    # Dropped one by one while on their way: one gap per record, each taken back as it arrives.
    for seq in range(7, 107):
        assert receive(seq + 100, seq + 1)[1] == 1
    for seq in range(7, 107):
        assert receive(seq, 1) == (False, 0)
    assert hop.stats()[TOPIC]["missing"] == 0


def test_a_restarted_publisher_s_first_record_counts_the_source_records_in_between_even_after_a_restart() -> None:
    first = HopIntake(window=100)
    keys = []
    for seq, source in ((1, 10), (2, 11), (3, 12)):
        keyed = keyed_hop_key(TOPIC, frame_key(7, seq, 1, source))
        assert keyed is not None
        first.check(TOPIC, *keyed)
        keys.append(keyed[0])
    keys.append(source_key(keys[-1], 12))
    # destination_server restarts too (one process): it has what it committed.
    hop = HopIntake(window=100)
    hop.load(HopKey(*k) for k in keys)
    keyed = keyed_hop_key(TOPIC, frame_key(8, 1, 1, 20))
    assert keyed is not None
    verdict = hop.check(TOPIC, *keyed)
    assert (verdict.skipped, verdict.first_skipped, verdict.source) == (7, 13, True)
    assert hop.stats()[TOPIC]["missing"] == 7
    # A source that started again (its numbers from 1) tells nothing.
    keyed = keyed_hop_key(TOPIC, frame_key(9, 1, 1, 1))
    assert keyed is not None
    assert hop.check(TOPIC, *keyed).skipped == 0


def test_a_loss_counted_before_a_restart_of_destination_server_is_not_counted_again_after_it() -> None:
    """What one run counted is committed with its records (a settled mark): the next run, loading the
    keys, takes the hole in them for what it is and counts only what is lost since."""
    first = HopIntake(window=100)
    committed: list[HopKey] = []

    def receive(hop: HopIntake, seq: int, low: int) -> int:
        keyed = keyed_hop_key(TOPIC, frame_key(7, seq, low))
        assert keyed is not None
        verdict = hop.check(TOPIC, keyed[0], keyed[1])
        hop.handled(keyed[0])
        committed.append(keyed[0])
        committed.extend(hop.take_settled_marks())  # handed over with the batch that counted
        return verdict.skipped

    for seq in range(1, 11):
        assert receive(first, seq, 1) == 0
    assert receive(first, 20, 15) == 4, "11..14 dropped by the publisher, unacknowledged"
    assert first.stats()[TOPIC]["missing"] == 4
    # destination_server restarts (killed, or stopped and started): the next run loads what was committed.
    second = HopIntake(window=100)
    second.load(committed)
    assert receive(second, 21, 16) == 1, "only 15 is new: 11..14 were counted by the first run"
    assert second.stats()[TOPIC]["missing"] == 1
    assert receive(second, 16, 16) == 0 and receive(second, 17, 16) == 0
    third = HopIntake(window=100)
    third.load(committed)
    assert receive(third, 30, 25) == 5, "18, 19 and 22..24: 16, 17, 20 and 21 arrived"
    # The marks are no publisher's records: the acks ignore them. Taken for writers of a topic
    # "<topic> <- settled", as many as MAX_ACK_WRITERS of them pushed the real publisher out of the tracker.
    tracker = AckTracker()
    tracker.saw(TOPIC, 7, 25)
    tracker.committed(committed)
    tracker.committed([(TOPIC + SETTLED_SUFFIX, -(100 + w), 5) for w in range(MAX_ACK_WRITERS)])
    assert tracker.acks() == [(TOPIC, 7, 24)]


def test_only_topics_destination_server_reads_are_kept() -> None:
    servers = {
        "destination_server": {
            "ros__parameters": {
                "destination_plugins": ["file", "pg"],
                "file": {"inputs": ["/dc/measurement/a", "/dc/group/g"]},
                "pg": {"inputs": ["/dc/measurement/b"]},
            }
        }
    }
    assert destination_inputs(servers) == {"/dc/measurement/a", "/dc/measurement/b", "/dc/group/g"}
    assert destination_inputs({}) == set()


class _Logger:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def get_child(self, name: str) -> _Logger:
        return self

    def error(self, line: str) -> None:
        self.lines.append(line)

    warning = info = error


class _Node:
    def __init__(self) -> None:
        self.logger = _Logger()

    def get_logger(self) -> _Logger:
        return self.logger


class _Publisher:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def publish(self, serialised: bytes) -> None:
        self.sent.append(serialised)


def test_a_publisher_beyond_its_limit_drops_the_oldest_counts_and_logs_them_and_says_so_in_its_keys() -> None:
    from dc_core.stamped_cdr import read_keyed_string_stamped

    node = _Node()
    sender = HandoffSender(node, HandoffParams(unacked_limit_records=2), [TOPIC])
    ros_publisher = _Publisher()
    publish = sender.output(TOPIC, ros_publisher)
    forwarding(41)
    try:
        publish(1, '{"n": 0}', "")
    finally:
        forwarding(0)
    for n in range(1, 4):
        publish(1 + n, f'{{"n": {n}}}', "")
    keys = [parse_frame_key(read_keyed_string_stamped(b)[2]) for b in ros_publisher.sent]
    # A record's low is the oldest held once it is: never one dropped to make room for it.
    assert [k[1:] if k else None for k in keys] == [(1, 1, 41), (2, 1, 0), (3, 2, 0), (4, 3, 0)]
    assert sender.metrics()[TOPIC]["dropped"] == 2 and sender.metrics()[TOPIC]["unacked"] == 2
    assert any("unacked_limit_records 2" in line for line in node.logger.lines), node.logger.lines
    other = sender.output("/not/read", _Publisher())
    other(1, "{}", "")
    assert "/not/read" not in sender.metrics(), "nothing is kept for a topic no destination_server reads"


def test_at_the_byte_limit_each_record_names_as_low_the_oldest_record_still_held() -> None:
    from dc_core.stamped_cdr import read_keyed_string_stamped

    sender = HandoffSender(_Node(), HandoffParams(unacked_limit_bytes=300), [TOPIC])
    ros_publisher = _Publisher()
    publish = sender.output(TOPIC, ros_publisher)
    for n in range(20):
        pad = "x" * (n * 7 % 50)
        publish(1 + n, f'{{"n": {n}, "pad": "{pad}"}}', "")
        key = parse_frame_key(read_keyed_string_stamped(ros_publisher.sent[-1])[2])
        assert key is not None
        held = sender.metrics()[TOPIC]
        assert held["unacked_bytes"] <= 300 + 8, held  # the key's digits may grow by a few bytes
        assert key[2] == key[1] - held["unacked"] + 1, (key, held)
