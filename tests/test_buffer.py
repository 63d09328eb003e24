"""The delivery buffer on its own: queues, limits, dead letters, corruption, restart.

The tests taking the ``buffer`` fixture are the suite of the ``Buffer`` protocol
(dc_destinations.buffer): they use its methods only and run against every implementation in
``BUFFERS``. A new buffer (another store) adds its factory there and must pass them. The tests
after them are SqliteBuffer's own (its file, WAL, corruption handling, `dc buffer`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import json
import os
import re
import sqlite3
import time
import tracemalloc
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dc_destinations import buffer_admin
from dc_destinations.buffer import (
    FILE_NAME,
    Buffer,
    BufferCorrupted,
    PendingRecord,
    Quarantine,
    QueueLimit,
    SqliteBuffer,
)
from tests.buffer_damage import damage_pages


def pending(n: int, width: int = 0) -> PendingRecord:
    payload = f'{{"n":"{n:08d}","pad":"{"x" * width}"}}'
    return PendingRecord(record_id=f"id-{n:08d}", topic="/dc/measurement/t", stamp_ns=n, payload=payload)


BUFFERS: dict[str, Callable[[Path], Buffer]] = {"sqlite": lambda folder: SqliteBuffer(folder / FILE_NAME)}


@pytest.fixture(params=sorted(BUFFERS))
def buffer(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Buffer]:
    b = BUFFERS[request.param](tmp_path)
    yield b
    b.close()


def test_append_read_delete(buffer: Buffer) -> None:
    result = buffer.append({"a": [pending(i) for i in range(10)], "b": [pending(100)]})
    assert result.appended == {"a": 10, "b": 1}
    rows = buffer.read_batch("a", 4)
    assert [r.record_id for r in rows] == [f"id-{i:08d}" for i in range(4)]
    assert buffer.delete("a", [r.row_id for r in rows]) == 4
    assert [r.record_id for r in buffer.read_batch("a", 100)] == [f"id-{i:08d}" for i in range(4, 10)]
    stats = buffer.stats("a")
    assert stats.rows == 6
    assert stats.bytes == sum(pending(i).size for i in range(4, 10))
    assert stats.received_total == 10 and stats.sent_total == 4
    assert buffer.stats("b").rows == 1  # queues are independent


def test_deleting_twice_counts_once(buffer: Buffer) -> None:
    buffer.append({"a": [pending(1)]})
    (row,) = buffer.read_batch("a", 10)
    assert buffer.delete("a", [row.row_id]) == 1
    assert buffer.delete("a", [row.row_id]) == 0
    assert buffer.stats("a").sent_total == 1


def test_failures_are_counted_per_row(buffer: Buffer) -> None:
    buffer.append({"a": [pending(1), pending(2)]})
    first, second = buffer.read_batch("a", 10)
    assert buffer.record_failure("a", [first.row_id]) == {first.row_id: 1}
    assert buffer.record_failure("a", [first.row_id, second.row_id]) == {first.row_id: 2, second.row_id: 1}
    assert [r.attempts for r in buffer.read_batch("a", 10)] == [2, 1]


def test_dead_letters_keep_the_error_and_can_be_replayed_or_purged(buffer: Buffer) -> None:
    buffer.append({"a": [pending(i) for i in range(3)]})
    rows = buffer.read_batch("a", 10)
    assert buffer.dead_letter("a", [(rows[0], "rejected: 400 bad field"), (rows[2], "rejected: too big")]) == 2
    assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000001"]
    letters = buffer.list_dead_letters("a")
    assert [(d.record_id, d.error) for d in letters] == [
        ("id-00000000", "rejected: 400 bad field"),
        ("id-00000002", "rejected: too big"),
    ]
    shown = buffer.get_dead_letter(letters[0].id)
    assert shown is not None and shown.payload == pending(0).payload
    assert buffer.stats("a").dead_letters == 2 and buffer.stats("a").dead_lettered_total == 2

    assert buffer.replay_dead_letters(ids=[letters[0].id]) == 1
    assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000001", "id-00000000"]
    assert buffer.read_batch("a", 10)[1].attempts == 0
    assert buffer.stats("a").rows == 2

    assert buffer.purge_dead_letters("a") == 1
    assert buffer.list_dead_letters() == []


def test_dead_letters_beyond_their_limit_lose_the_oldest_of_their_destination_only(buffer: Buffer) -> None:
    size = pending(0).size
    buffer.append({"a": [pending(i) for i in range(6)], "b": [pending(100)]})
    buffer.dead_letter("a", [(row, "rejected") for row in buffer.read_batch("a", 10)])
    buffer.dead_letter("b", [(row, "rejected") for row in buffer.read_batch("b", 10)])

    assert buffer.trim_dead_letters("a", 6 * size) == 0  # exactly at the limit: nothing to do
    assert buffer.trim_dead_letters("a", 4 * size + 1) == 2
    assert [d.record_id for d in buffer.list_dead_letters("a")] == [f"id-{i:08d}" for i in range(2, 6)]
    assert [d.record_id for d in buffer.list_dead_letters("b")] == ["id-00000100"]
    assert buffer.trim_dead_letters("a", 0) == 4
    assert buffer.list_dead_letters("a") == [] and buffer.stats("b").dead_letters == 1


def test_dead_letter_limit_counts_what_replay_and_purge_removed(buffer: Buffer) -> None:
    size = pending(0).size
    buffer.append({"a": [pending(i) for i in range(6)]})
    buffer.dead_letter("a", [(row, "rejected") for row in buffer.read_batch("a", 10)])
    letters = buffer.list_dead_letters("a")
    buffer.purge_dead_letters("a", [letters[0].id])
    buffer.replay_dead_letters("a", [letters[1].id])
    # Four left: a limit of three deletes one, the oldest of them, not three.
    assert buffer.trim_dead_letters("a", 3 * size) == 1
    assert [d.record_id for d in buffer.list_dead_letters("a")] == [f"id-{i:08d}" for i in range(3, 6)]
    buffer.dead_letter("a", [(row, "rejected again") for row in buffer.read_batch("a", 10)])
    assert buffer.trim_dead_letters("a", 3 * size) == 1


def test_a_buffer_of_schema_1_is_migrated_with_its_dead_letters_counted(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    size = pending(0).size
    old = SqliteBuffer(path)
    old.append({"a": [pending(i) for i in range(5)]})
    old.dead_letter("a", [(row, "rejected") for row in old.read_batch("a", 10)])
    old.close()
    # What DC wrote before dead_bytes existed: no column, no triggers, version 1.
    conn = sqlite3.connect(path)
    conn.executescript(
        "DROP TRIGGER dead_letter_added; DROP TRIGGER dead_letter_removed;"
        "ALTER TABLE queues DROP COLUMN dead_bytes; UPDATE meta SET value = '1' WHERE key = 'schema_version';"
    )
    conn.close()

    migrated = SqliteBuffer(path)
    try:
        assert migrated.trim_dead_letters("a", 3 * size) == 2
        assert [d.record_id for d in migrated.list_dead_letters("a")] == [f"id-{i:08d}" for i in range(2, 5)]
    finally:
        migrated.close()
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone() == ("3",)
    conn.close()


def test_read_batch_after_a_row(buffer: Buffer) -> None:
    buffer.append({"a": [pending(i) for i in range(10)]})
    first = buffer.read_batch("a", 4)
    after = buffer.read_batch("a", 4, after_id=first[-1].row_id)
    assert [r.record_id for r in after] == [f"id-{i:08d}" for i in range(4, 8)]
    assert buffer.read_batch("a", 4, after_id=after[-1].row_id + 100) == []


def test_only_a_checked_payload_unchanged_since_is_known_as_appended(buffer: Buffer) -> None:
    checked = PendingRecord("id-c", "/t", 1, '{"n":1}', checked=True)
    buffer.append({"a": [checked, pending(2)]})
    first, second = buffer.read_batch("a", 10)
    assert first.as_appended(), "a payload appended as DC JSON for certain"
    assert not second.as_appended(), "nobody checked it"
    buffer.dead_letter("a", [(first, "rejected")])
    buffer.replay_dead_letters("a")
    (replayed,) = [r for r in buffer.read_batch("a", 10) if r.record_id == "id-c"]
    assert not replayed.as_appended(), "a dead letter comes back unchecked: it may be why it died"


def test_a_payload_changed_by_hand_is_no_longer_known_as_appended(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    buffer = SqliteBuffer(path)
    buffer.append({"a": [PendingRecord("id-1", "/t", 1, '{"v":1.5}', checked=True)]})
    conn = sqlite3.connect(path)
    conn.execute("""UPDATE q_1 SET payload = '{"v":NaN}'""")
    conn.commit()
    conn.close()
    try:
        (row,) = buffer.read_batch("a", 1)
        assert row.payload == '{"v":NaN}' and row.payload_crc is not None
        assert not row.as_appended()
    finally:
        buffer.close()


def test_queues_of_schema_2_get_the_crc_column_and_their_rows_none(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    old = SqliteBuffer(path)
    old.append({"a": [PendingRecord("id-1", "/t", 1, '{"v":NaN}')]})
    old.close()
    # What DC wrote before payload_crc existed, the queue table included.
    conn = sqlite3.connect(path)
    conn.executescript(
        "ALTER TABLE q_1 DROP COLUMN payload_crc; UPDATE meta SET value = '2' WHERE key = 'schema_version';"
    )
    conn.close()
    migrated = SqliteBuffer(path)
    try:
        (row,) = migrated.read_batch("a", 10)
        assert row.payload_crc is None and not row.as_appended()
        migrated.append({"a": [PendingRecord("id-2", "/t", 2, '{"v":2}', checked=True)]})
        assert [r.as_appended() for r in migrated.read_batch("a", 10)] == [False, True]
    finally:
        migrated.close()


def test_size_limit_drop_newest_keeps_the_oldest(buffer: Buffer) -> None:
    size = pending(0).size
    limit = {"a": QueueLimit(max_bytes=10 * size, drop_oldest=False)}
    result = buffer.append({"a": [pending(i) for i in range(7)]}, limit)
    assert result.appended == {"a": 7} and not result.dropped_newest
    result = buffer.append({"a": [pending(i) for i in range(7, 14)]}, limit)
    assert result.appended == {"a": 3} and result.dropped_newest == {"a": 4}
    assert result.dropped_ids == {"a": [f"id-{i:08d}" for i in range(10, 14)]}
    assert result.dropped_topics == {"a": {"/dc/measurement/t": 4}}  # counted per measurement
    kept = [r.record_id for r in buffer.read_batch("a", 100)]
    assert kept == [f"id-{i:08d}" for i in range(10)]
    stats = buffer.stats("a")
    assert stats.bytes == 10 * size and stats.dropped_total == 4 and stats.received_total == 14


def test_size_limit_drop_oldest_keeps_the_newest(buffer: Buffer) -> None:
    size = pending(0).size
    limit = {"a": QueueLimit(max_bytes=10 * size, drop_oldest=True)}
    buffer.append({"a": [pending(i) for i in range(7)]}, limit)
    result = buffer.append({"a": [pending(i) for i in range(7, 14)]}, limit)
    assert result.appended == {"a": 7} and result.dropped_oldest == {"a": 4}
    assert result.dropped_ids == {"a": [f"id-{i:08d}" for i in range(4)]}
    assert result.dropped_topics == {"a": {"/dc/measurement/t": 4}}
    kept = [r.record_id for r in buffer.read_batch("a", 100)]
    assert kept == [f"id-{i:08d}" for i in range(4, 14)]
    # A batch bigger than the whole limit keeps its newest records.
    result = buffer.append({"a": [pending(i) for i in range(100, 125)]}, limit)
    assert [r.record_id for r in buffer.read_batch("a", 100)] == [f"id-{i:08d}" for i in range(115, 125)]
    assert buffer.stats("a").bytes == 10 * size
    assert buffer.stats("a").dropped_total == 4 + 10 + 15


@pytest.mark.parametrize("drop_oldest", [True, False])
def test_a_record_bigger_than_the_limit_is_dropped_alone(buffer: Buffer, drop_oldest: bool) -> None:
    limit = {"a": QueueLimit(max_bytes=200, drop_oldest=drop_oldest)}
    buffer.append({"a": [pending(1)]}, limit)
    result = buffer.append({"a": [pending(2, width=500)]}, limit)
    assert result.appended == {"a": 0}
    assert result.dropped_newest == {"a": 1}
    assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000001"]


def test_counts_survive_a_restart(tmp_path: Path) -> None:
    first = SqliteBuffer(tmp_path / FILE_NAME)
    first.append({"a": [pending(i) for i in range(5)]})
    first.close()
    second = SqliteBuffer(tmp_path / FILE_NAME, synchronous="full")
    try:
        stats = second.stats("a")
        assert (stats.rows, stats.received_total) == (5, 5)
        assert stats.bytes == sum(pending(i).size for i in range(5))
        assert len(second.read_batch("a", 10)) == 5
    finally:
        second.close()


def test_a_file_that_is_not_a_database_is_moved_aside(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    path.write_bytes(b"this is not SQLite" * 1000)
    seen: list[Quarantine] = []
    buffer = SqliteBuffer(path, on_quarantine=seen.append)
    try:
        assert len(seen) == 1
        assert seen[0].moved_to.exists() and seen[0].moved_to.name.startswith(f"{FILE_NAME}.corrupt-")
        assert seen[0].moved_to.read_bytes().startswith(b"this is not SQLite")
        buffer.append({"a": [pending(1)]})
        assert len(buffer.read_batch("a", 10)) == 1
    finally:
        buffer.close()


def _fill(path: Path, count: int, width: int = 150) -> None:
    buffer = SqliteBuffer(path)
    for start in range(0, count, 2000):
        buffer.append({"a": [pending(i, width) for i in range(start, min(start + 2000, count))]})
    buffer.close()


def test_damaged_pages_are_found_and_the_buffer_replaced(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    _fill(path, 5000)
    page_size = 4096
    size = path.stat().st_size
    with path.open("r+b") as handle:  # scribble over every page but the first (the schema's root)
        for offset in range(page_size, size, page_size):
            handle.seek(offset)
            handle.write(os.urandom(64))
    seen: list[Quarantine] = []
    buffer = SqliteBuffer(path, on_quarantine=seen.append)
    try:
        try:
            buffer.read_batch("a", 500)
            buffer.stats("a")
        except BufferCorrupted:
            pass
        assert len(seen) == 1, "the damage must be found at start or at the first read"
        buffer.append({"a": [pending(1)]})
        assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000001"]
    finally:
        buffer.close()


def test_restart_streams_a_large_backlog_in_bounded_memory(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    count = 100_000
    _fill(path, count)  # ~20 MB of records
    gc.collect()
    tracemalloc.start()
    try:
        started = time.monotonic()
        buffer = SqliteBuffer(path)
        opened_in = time.monotonic() - started
        seen = 0
        while rows := buffer.read_batch("a", 500):
            seen += len(rows)
            buffer.delete("a", [r.row_id for r in rows])
        _current, peak = tracemalloc.get_traced_memory()
        buffer.close()
    finally:
        tracemalloc.stop()
    assert seen == count
    assert opened_in < 1.0
    assert peak < 4 * 1024 * 1024, f"peak Python memory {peak / 1e6:.1f} MB while streaming 20 MB"


def test_another_connection_can_work_while_the_buffer_is_open(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    server = SqliteBuffer(path)
    try:
        server.append({"a": [pending(1)]})
        (row,) = server.read_batch("a", 1)
        server.dead_letter("a", [(row, "rejected")])
        admin = SqliteBuffer(path)
        try:
            assert admin.replay_dead_letters("a") == 1
        finally:
            admin.close()
        assert [r.record_id for r in server.read_batch("a", 10)] == ["id-00000001"]
        assert server.stats("a").rows == 1
    finally:
        server.close()


def test_wal_mode_and_sync_setting(tmp_path: Path) -> None:
    buffer = SqliteBuffer(tmp_path / FILE_NAME, synchronous="full")
    buffer.close()
    conn = sqlite3.connect(tmp_path / FILE_NAME)
    try:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    finally:
        conn.close()


# -- dc buffer (buffer_admin) ------------------------------------------------------------------


def _cli(tmp_path: Path, action: str, *ids: str, destination: str = "", all_: bool = False) -> tuple[int, str]:
    args = argparse.Namespace(
        action=action,
        ids=list(ids),
        storage_path=str(tmp_path),
        params="",
        namespace="/",
        destination=destination,
        all=all_,
    )
    out = io.StringIO()
    code = buffer_admin.run_cli(args, out)
    return code, out.getvalue()


def _with_dead_letters(tmp_path: Path) -> list[int]:
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        buffer.append({"a": [pending(i) for i in range(3)], "b": [pending(9)]})
        buffer.dead_letter("a", [(row, f"rejected: 422 row {i}") for i, row in enumerate(buffer.read_batch("a", 10))])
        buffer.dead_letter("b", [(row, "rejected: 400") for row in buffer.read_batch("b", 10)])
        return [d.id for d in buffer.list_dead_letters()]
    finally:
        buffer.close()


def test_dc_buffer_list_show_replay_purge(tmp_path: Path) -> None:
    ids = _with_dead_letters(tmp_path)
    code, text = _cli(tmp_path, "list")
    assert code == 0
    assert "rejected: 422 row 1" in text and "id-00000009" in text
    code, text = _cli(tmp_path, "show", str(ids[0]))
    shown = json.loads(text)
    assert shown["payload"] == {"n": "00000000", "pad": ""} and shown["error"] == "rejected: 422 row 0"
    assert _cli(tmp_path, "replay")[0] == 1  # nothing said what to replay
    code, text = _cli(tmp_path, "replay", destination="a")
    assert (code, text.strip()) == (0, "replayed 3 dead letter(s) into their queues")
    code, text = _cli(tmp_path, "stats")
    assert code == 0 and "a" in text
    assert [s.rows for s in buffer_admin.queue_stats(tmp_path / FILE_NAME)] == [3, 0]
    code, text = _cli(tmp_path, "purge", all_=True)
    assert (code, text.strip()) == (0, "purged 1 dead letter(s)")
    assert buffer_admin.list_dead_letters(tmp_path / FILE_NAME) == []


def test_dc_buffer_without_a_buffer_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _cli(tmp_path / "nowhere", "list")[0] == 1
    assert "no buffer at" in capsys.readouterr().err
    assert not (tmp_path / "nowhere").exists()


def test_dc_buffer_finds_the_storage_path_in_a_parameter_file(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(f'destination_server:\n  ros__parameters:\n    flb:\n      storage_path: "{tmp_path}/buf"\n')
    assert buffer_admin.storage_file(params_file=str(params)) == tmp_path / "buf" / FILE_NAME
    # A Nav2-style file: each robot's section under its namespace, read as the server reads it.
    params.write_text(
        f'/r1/destination_server:\n  ros__parameters:\n    flb.storage_path: "{tmp_path}/r1"\n'
        f'/r2:\n  destination_server:\n    ros__parameters:\n      flb.storage_path: "{tmp_path}/r2"\n'
    )
    assert buffer_admin.storage_file(params_file=str(params), namespace="/r2") == tmp_path / "r2" / FILE_NAME


def test_dc_buffer_leaves_a_corrupt_file_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / FILE_NAME).write_bytes(b"garbage" * 1000)
    assert _cli(tmp_path, "list")[0] == 1
    assert "corrupt" in capsys.readouterr().err
    assert (tmp_path / FILE_NAME).read_bytes().startswith(b"garbage")


# -- a damaged file: salvage ---------------------------------------------------------------------


def _backlog(path: Path, count: int) -> None:
    buffer = SqliteBuffer(path)
    try:
        for start in range(0, count, 1000):
            batch = [pending(i, 150) for i in range(start, min(start + 1000, count))]
            buffer.append({"a": batch, "b": batch[:10] if start == 0 else []})
        buffer.dead_letter("b", [(row, "rejected: 400") for row in buffer.read_batch("b", 4)])
    finally:
        buffer.close()


def test_damaged_pages_cost_only_their_rows_the_rest_is_salvaged(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    _backlog(path, 5000)
    damage_pages(path)
    seen: list[Quarantine] = []
    buffer = SqliteBuffer(path, on_quarantine=seen.append)
    try:
        if not seen:  # the damage lies past the queues' heads: found by the integrity check
            assert buffer.quick_check() != "ok"
            buffer.set_aside("integrity check")
        assert len(seen) == 1
        report = seen[0].salvage
        assert report is not None and not seen[0].salvage_error
        assert report.recovered["a"] + report.lost.get("a", 0) == 5000
        assert report.recovered["a"] >= 4750, report.summary()
        assert report.recovered.get("b", 0) + report.lost.get("b", 0) == 6  # 10 queued, 4 dead-lettered
        assert report.dead_letters_recovered == 4
        assert not report.lost_unknown_count
        rows: list[str] = []
        after = 0
        while batch := buffer.read_batch("a", 1000, after_id=after):
            after = batch[-1].row_id
            rows += [r.record_id for r in batch]
            # Same record_id and same id as in the old file: a batch read before the set-aside is
            # still deleted when delivered.
            assert all(r.row_id == int(r.record_id[3:]) + 1 for r in batch)
        assert len(rows) == report.recovered["a"] == buffer.stats("a").rows
        assert rows == sorted(set(rows)), "in their order, once each"
        assert buffer.stats("a").received_total == 5000, "lifetime totals carried over"
        assert [d.error for d in buffer.list_dead_letters("b")] == ["rejected: 400"] * 4
        assert "lost to the damage" in report.summary()
        assert buffer.quick_check() == "ok"
    finally:
        buffer.close()
    assert seen[0].moved_to.exists(), "the damaged file is kept"


def test_salvage_counts_as_unknown_what_it_cannot_name(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    _backlog(path, 100)
    conn = sqlite3.connect(path)
    (queues_root,) = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'queues'").fetchone()
    conn.close()
    with path.open("r+b") as handle:  # the table naming each queue's destination
        handle.seek((queues_root - 1) * 4096)
        handle.write(b"\xff" * 4096)
    target = SqliteBuffer(tmp_path / "new" / FILE_NAME)
    try:
        report = target.salvage(path)
    finally:
        target.close()
    assert report.recovered == {}
    assert report.lost == {"(unknown)": 106} and report.lost_unknown_count  # 110 queued, 4 dead-lettered


def test_quick_check_finds_damage_of_the_file_in_use(tmp_path: Path) -> None:
    path = tmp_path / FILE_NAME
    _backlog(path, 3000)
    buffer = SqliteBuffer(path)
    try:
        assert buffer.quick_check() == "ok"
        damage_pages(path, 3)
        assert buffer.quick_check() != "ok"
    finally:
        buffer.close()


def test_dc_buffer_salvage_puts_a_set_aside_file_into_a_buffer(tmp_path: Path) -> None:
    damaged = tmp_path / "old" / f"{FILE_NAME}.corrupt-20260101T000000Z"
    damaged.parent.mkdir()
    _backlog(damaged, 5000)
    damage_pages(damaged)
    before = damaged.read_bytes()
    live = SqliteBuffer(tmp_path / FILE_NAME)  # a buffer in use, with records of its own
    live.append({"a": [pending(i) for i in range(90_000, 90_010)]})
    live.close()
    args = argparse.Namespace(
        action="salvage",
        ids=[str(damaged)],
        storage_path="",
        params="",
        namespace="/",
        destination="",
        all=False,
        into=str(tmp_path),
    )
    out = io.StringIO()
    assert buffer_admin.run_cli(args, out) == 0
    text = out.getvalue()
    numbers = re.search(r"records recovered (\d+) \(a (\d+), b (\d+)\); lost to the damage (\d+) \(a (\d+)", text)
    assert numbers, text
    total, in_a, in_b, lost, lost_a = map(int, numbers.groups())
    assert in_a + lost_a == 5000 and in_a >= 4750 and total == in_a + in_b and lost >= lost_a
    assert "dead letters recovered 4" in text
    assert damaged.read_bytes() == before, "the damaged file is only read"
    stats = {s.destination: s for s in buffer_admin.queue_stats(tmp_path / FILE_NAME)}
    assert stats["a"].rows == 10 + in_a
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        assert buffer.read_batch("a", 10)[0].record_id == "id-00090000", "the buffer's own records stay first"
    finally:
        buffer.close()


def test_dc_buffer_salvage_says_what_is_wrong(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def salvage(*files: str, into: str) -> int:
        args = argparse.Namespace(
            action="salvage", ids=list(files), storage_path="", params="", namespace="/", into=into
        )
        return buffer_admin.run_cli(args, io.StringIO())

    assert salvage(str(tmp_path / "nothing"), into=str(tmp_path)) == 1
    assert "no file" in capsys.readouterr().err
    assert salvage(into=str(tmp_path)) == 1
    assert "give the set-aside file" in capsys.readouterr().err
    _backlog(tmp_path / FILE_NAME, 10)
    assert salvage(str(tmp_path / FILE_NAME), into=str(tmp_path)) == 1
    assert "is this buffer itself" in capsys.readouterr().err
    assert buffer_admin.queue_stats(tmp_path / FILE_NAME)[0].rows == 10


def test_a_row_read_with_the_wrong_types_is_counted_not_queued(tmp_path: Path) -> None:
    source = tmp_path / "old.sqlite3"
    _backlog(source, 20)
    with contextlib.closing(sqlite3.connect(source)) as conn:  # as a damaged page can read
        conn.execute("UPDATE q_1 SET payload = x'00ff' WHERE id = 5")
        conn.execute("UPDATE q_1 SET stamp_ns = x'01' WHERE id = 6")
        conn.commit()
    target = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        report = target.salvage(source)
        assert (report.recovered["a"], report.lost["a"]) == (18, 2)
        assert all(isinstance(r.payload, str) for r in target.read_batch("a", 100))
        assert target.stats("a").bytes == sum(r.size for r in target.read_batch("a", 100))
    finally:
        target.close()


def test_a_record_lost_to_the_damage_never_lends_its_id_to_a_new_one(tmp_path: Path) -> None:
    """A sender holds rows read before the file was set aside; the damage took them. Deleting them
    once delivered must not delete the new records written since (the old ids are not reused)."""
    path = tmp_path / FILE_NAME
    buffer = SqliteBuffer(path)
    try:
        buffer.append({"a": [pending(i) for i in range(10)]})
        in_flight = buffer.read_batch("a", 10)
        with contextlib.closing(sqlite3.connect(path)) as other:
            other.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
        with path.open("r+b") as handle:  # nothing of the file can be read any more
            handle.write(b"\xff" * path.stat().st_size)
        quarantine = buffer.set_aside("damaged under a sender")
        assert quarantine is not None and quarantine.salvage is not None and quarantine.salvage.recovered == {}
        buffer.append({"a": [pending(100), pending(101)]})
        assert buffer.delete("a", [row.row_id for row in in_flight]) == 0
        assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000100", "id-00000101"]
        buffer.append({"a": [pending(102)]})
        assert buffer.stats("a").rows == 3
    finally:
        buffer.close()


def test_a_drop_oldest_that_empties_the_queue_never_lends_a_read_rows_id_to_a_new_record(buffer: Buffer) -> None:
    """A sender holds rows it read; a batch as large as the limit drops the whole queue, those rows
    with it. The sender's delete of the rows it sent must not delete the new records: SQLite gives a
    table emptied of its largest ids those ids again, unless the buffer keeps new rows above them."""
    size = pending(0).size
    limit = {"a": QueueLimit(max_bytes=10 * size, drop_oldest=True)}
    buffer.append({"a": [pending(i) for i in range(10)]}, limit)
    held = buffer.read_batch("a", 10)  # a send() under way
    result = buffer.append({"a": [pending(i) for i in range(100, 110)]}, limit)
    assert result.dropped_oldest == {"a": 10}
    assert sorted(result.dropped_ids["a"]) == [f"id-{i:08d}" for i in range(10)]
    assert buffer.delete("a", [row.row_id for row in held]) == 0, "the held rows were dropped"
    assert [r.record_id for r in buffer.read_batch("a", 100)] == [f"id-{i:08d}" for i in range(100, 110)]


def test_the_size_limit_drops_no_record_in_a_send_before_its_outcome(buffer: Buffer) -> None:
    """A record the size limit dropped while its send() ran, then confirmed by the destination, was
    counted twice: dropped, and sent. Rows held for a send() that the limit chooses stay until the
    send's outcome: confirmed, they are sent; failed, they go then, counted dropped once."""
    size = pending(0).size
    limit = {"a": QueueLimit(max_bytes=10 * size, drop_oldest=True)}
    buffer.append({"a": [pending(i) for i in range(10)]}, limit)
    in_send = buffer.read_batch("a", 4)
    buffer.hold("a", [row.row_id for row in in_send])
    result = buffer.append({"a": [pending(i) for i in range(100, 106)]}, limit)
    # The six oldest were chosen: the four in the send stay until it answers, two others go now.
    assert result.dropped_ids == {"a": ["id-00000004", "id-00000005"]}
    assert buffer.stats("a").rows == 14  # above the limit by the rows in the send
    assert buffer.delete("a", [row.row_id for row in in_send[:2]]) == 2  # confirmed: sent, not dropped
    dropped: list[str] = []
    topics: Counter[str] = Counter()
    failed = [row.row_id for row in in_send[2:]]
    assert buffer.record_failure("a", failed, dropped_ids=dropped, dropped_topics=topics) == {
        in_send[2].row_id: 1,
        in_send[3].row_id: 1,
    }
    assert dropped == ["id-00000002", "id-00000003"]  # failed: they go now
    assert topics == {"/dc/measurement/t": 2}
    stats = buffer.stats("a")
    assert (stats.rows, stats.bytes) == (10, 10 * size)
    assert stats.received_total == stats.sent_total + stats.dropped_total + stats.rows == 16
    assert [r.record_id for r in buffer.read_batch("a", 100)] == [
        f"id-{i:08d}" for i in (*range(6, 10), *range(100, 106))
    ]
    # Released (a sender reading from the head again), rows are the limit's as any others.
    again = buffer.read_batch("a", 2)
    buffer.hold("a", [row.row_id for row in again])
    buffer.release("a")
    assert buffer.append({"a": [pending(200)]}, limit).dropped_ids == {"a": ["id-00000006"]}


def test_evict_oldest_names_the_records_it_evicts(buffer: Buffer) -> None:
    buffer.append({"a": [pending(i) for i in range(10)]})
    assert buffer.read_batch("a", 2)  # read: left alone
    evicted = buffer.evict_oldest("a", 3 * pending(0).size, with_ids=True)
    assert (evicted.records, evicted.record_ids) == (3, [f"id-{i:08d}" for i in range(2, 5)])
    assert buffer.evict_oldest("a", 1).record_ids == []  # not asked for


def test_dead_letter_names_only_the_rows_it_moved(buffer: Buffer) -> None:
    """A row the size limit dropped while its send failed has no dead letter: whoever is told of dead
    letters (dc ingest acknowledges their messages) must not hear of it."""
    size = pending(0).size
    limit = {"a": QueueLimit(max_bytes=4 * size, drop_oldest=True)}
    buffer.append({"a": [pending(i) for i in range(4)]}, limit)
    failed = buffer.read_batch("a", 4)
    buffer.append({"a": [pending(i) for i in range(10, 12)]}, limit)  # drops the two oldest
    moved: list[str] = []
    assert buffer.dead_letter("a", [(row, "refused") for row in failed], moved_ids=moved) == 2
    assert moved == ["id-00000002", "id-00000003"]
    assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000010", "id-00000011"]


CAMERA, HEALTH = "/dc/measurement/camera", "/dc/measurement/health"


def of_topic(n: int, topic: str) -> PendingRecord:
    record = pending(n)
    return PendingRecord(record.record_id, topic, record.stamp_ns, record.payload)


def test_eviction_among_queues_takes_the_oldest_of_the_topics_named(buffer: Buffer) -> None:
    """What the disk budget evicts of one retention priority: the oldest records across the queues
    named, of only the input topics named in a queue whose topics have priorities of their own."""
    size = pending(0).size
    buffer.track_topics(["a"])
    buffer.append({"a": [of_topic(0, CAMERA), of_topic(1, HEALTH)]}, now_ns=1)
    buffer.append({"b": [of_topic(10, HEALTH)]}, now_ns=2)
    buffer.append({"a": [of_topic(2, CAMERA), of_topic(3, HEALTH)]}, now_ns=3)
    assert buffer.queued_topics("a") == {CAMERA: 2 * size, HEALTH: 2 * size}
    gone = buffer.evict_oldest_among({"a": [CAMERA], "b": None}, 2 * size, with_ids=True)
    assert {name: (e.record_ids, e.by_topic) for name, e in gone.items()} == {
        "a": (["id-00000000"], {CAMERA: 1}),
        "b": (["id-00000010"], {HEALTH: 1}),
    }
    # All there are when fewer: never a record of a topic not named.
    gone = buffer.evict_oldest_among({"a": [CAMERA], "b": None}, 100 * size)
    assert (gone["a"].records, gone["a"].bytes, gone["a"].record_ids) == (1, size, []) and "b" not in gone
    assert buffer.evict_oldest_among({"a": [CAMERA]}, size) == {}
    assert buffer.queued_topics("a") == {HEALTH: 2 * size}
    assert [r.record_id for r in buffer.read_batch("a", 10)] == ["id-00000001", "id-00000003"]
    assert buffer.stats("a").bytes == 2 * size and buffer.stats("b").rows == 0


def test_queued_topics_follows_every_change_of_a_queue(buffer: Buffer) -> None:
    """Per topic, what waits stays right through commits, the size limit, deliveries, dead letters,
    evictions and a replay (the last one counted again, as a change made by `dc buffer` would be)."""
    size = pending(0).size
    buffer.track_topics(["a"])
    kept: dict[str, str] = {}  # record_id -> topic of what waits

    def expected() -> dict[str, int]:
        return {t: size * list(kept.values()).count(t) for t in set(kept.values())}

    def add(first: int, count: int, limit: QueueLimit | None = None) -> None:
        records = [of_topic(n, CAMERA if n % 3 else HEALTH) for n in range(first, first + count)]
        result = buffer.append({"a": records}, {"a": limit} if limit else None)
        kept.update((r.record_id, r.topic) for r in records)
        for record_id in result.dropped_ids.get("a", []):
            del kept[record_id]

    add(0, 10)
    assert buffer.queued_topics("a") == expected()  # counted from the table, then kept
    for record_id in buffer.evict_oldest_among({"a": [CAMERA]}, 2 * size, with_ids=True)["a"].record_ids:
        del kept[record_id]
    for record_id in buffer.evict_oldest("a", size, with_ids=True).record_ids:
        del kept[record_id]
    add(10, 5, QueueLimit(max_bytes=10 * size, drop_oldest=True))
    assert buffer.queued_topics("a") == expected()
    first, second, *_ = buffer.read_batch("a", 3)
    buffer.delete("a", [first.row_id])
    buffer.dead_letter("a", [(second, "refused")])
    del kept[first.record_id], kept[second.record_id]
    assert buffer.queued_topics("a") == expected()
    assert buffer.replay_dead_letters("a") == 1
    kept[second.record_id] = second.topic
    assert buffer.queued_topics("a") == expected()
    assert sum(expected().values()) == buffer.stats("a").bytes


def test_a_buffer_written_before_topics_were_tracked_opens_indexed_and_delivers(tmp_path: Path) -> None:
    """The queues of an earlier DC (the same schema, no index by topic): a destination given
    priorities per topic gets its index at start and its rows counted and delivered; without them
    again, the index goes (it costs on every commit)."""
    earlier = SqliteBuffer(tmp_path / FILE_NAME)
    earlier.append({"a": [of_topic(n, CAMERA if n % 2 else HEALTH) for n in range(6)]})
    earlier.close()

    def indexes() -> list[str]:
        with contextlib.closing(sqlite3.connect(tmp_path / FILE_NAME)) as conn:
            found = conn.execute("SELECT name FROM sqlite_master WHERE type = 'index' AND name LIKE 'q_%'")
            return [row[0] for row in found]

    assert not indexes()
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    buffer.track_topics(["a"])
    assert indexes() == ["q_1_by_topic"]
    size = pending(0).size
    assert buffer.queued_topics("a") == {CAMERA: 3 * size, HEALTH: 3 * size}
    assert buffer.evict_oldest_among({"a": [CAMERA]}, size)["a"].by_topic == {CAMERA: 1}
    rows = buffer.read_batch("a", 10)
    assert [r.record_id for r in rows] == [f"id-{n:08d}" for n in (0, 2, 3, 4, 5)]
    assert buffer.delete("a", [r.row_id for r in rows]) == 5
    buffer.track_topics([])
    assert not indexes()
    buffer.close()
