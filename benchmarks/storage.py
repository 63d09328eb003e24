"""Storage destinations against their own server's fastest load, in one run (no ROS).

    .venv/bin/python benchmarks/storage.py [--records 100000] [--runs 3] [--only pgsql,s3,files]
                                           [--batch-sizes 500,5000] [--label NAME] [--profile]

Starts a throw-away PostgreSQL and SeaweedFS S3 gateway on 127.0.0.1 (dc_bringup.local_servers) and
measures, in this process and the same run:

- pgsql: --records records of ~200 bytes of JSON written into a DC buffer while the destination is
  down, then drained by the delivery layer (buffer, sender, PgSQL destination, as destination_server
  runs them) into a fresh table. Baseline on the same server: psycopg's ``COPY … FROM STDIN`` of the
  same rows, in one transaction, into a table of the same shape and unique index (text; the same
  in binary is measured too). To tell apart what costs what, also, without the buffer: per batch,
  one binary COPY straight into the table (the destination's statement: the most its send() can
  reach); per batch, COPY into a temporary table then ``INSERT … SELECT … ON CONFLICT`` (its way
  when a record of the batch is in the table already); the pipelined ``INSERT … ON CONFLICT`` it
  used before; and the buffer drained into a destination that discards.
- s3: the same kind of buffer drained by the S3 destination: objects/s and MB/s of JSON lines;
  baseline: boto3 ``put_object`` of the same bytes cut into the same objects.
- files: files uploaded by the MinIO destination's ``send()`` against boto3's ``upload_file`` of
  the same files to other keys, small and large files separately; the two take turns going first.

A batched path is timed from the end of its first unit (batch, object) to the end of its last, so
that opening its connection with the first batch does not count; a path of one unit (COPY) and the
file uploads are timed whole. MB are 2^20 bytes of JSON lines or file. CPU: this whole process
(client) and the server's process tree, over the same window. Each figure is the median of --runs
runs; ratios are taken within each run, then their median. --profile writes cProfile statistics of
the sender thread of the first run's PgSQL drains to the temporary folder and prints them.
JSON in benchmarks/results/storage_<date>_<label>.json.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import datetime as dt
import functools
import gc
import io
import json
import os
import platform
import pstats
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import psutil

from dc_bringup.local_servers.postgres import PostgresServer
from dc_bringup.local_servers.seaweedfs import SeaweedS3Server
from dc_core.destination import Destination, OutgoingRecord, RetryableError, SendOutcome
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations import delivery
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.record_ids import new_record_id
from dc_destinations.sender import Sender
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

REPO = Path(__file__).resolve().parent.parent
PARTS = ("pgsql", "s3", "files")
DEFAULT_BATCH = DestinationDeliveryParams().batch_size
EPOCH = dt.datetime(1970, 1, 1)

# ~200 bytes of JSON, like the records of the other delivery benchmarks.
_DATA = {
    "cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]},
    "memory": {"used": 123456789, "percent": 45.6},
    "robot_name": "bench",
    "id": "robot-1",
    "run_id": "3",
    "name": "system",
}


class _Silent:
    """For the fill, whose destination fails on purpose."""

    def debug(self, message: str, /, **kwargs: Any) -> None:
        pass

    info = warning = error = debug


def _context(name: str) -> FakeContext:
    # Messages at warning and above still reach stderr through logging's last resort.
    return FakeContext(name=name, logger=RecordingLogger(f"dc.bench.{name}"))


# -- measuring -------------------------------------------------------------------------------------


def _client_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _tree_cpu(pid: int) -> float:
    """CPU seconds of a server: the process, its reaped children and its live ones (PostgreSQL's backends)."""
    try:
        root = psutil.Process(pid)
        times = root.cpu_times()
        total = times.user + times.system + times.children_user + times.children_system
        for child in root.children(recursive=True):
            with contextlib.suppress(psutil.NoSuchProcess):
                child_times = child.cpu_times()
                total += child_times.user + child_times.system
    except psutil.NoSuchProcess:
        return float("nan")
    return total


@dataclass
class Figure:
    """What crossed one window (see :class:`Window`)."""

    units: int = 0  # rows, objects or files counted in the window
    bytes: int = 0
    seconds: float = 0.0
    client_cpu_s: float = 0.0
    server_cpu_s: float = 0.0
    first_unit: int = 0  # units of the first mark, outside the window

    @property
    def per_s(self) -> float:
        return self.units / self.seconds if self.seconds > 0 else float("nan")

    @property
    def mb_per_s(self) -> float:
        return self.bytes / 2**20 / self.seconds if self.seconds > 0 else float("nan")

    def cpu_ms_per_1000(self, which: str) -> float:
        cpu = self.client_cpu_s if which == "client" else self.server_cpu_s
        return cpu / self.units * 1e6 if self.units else float("nan")

    def cpu_percent(self, which: str) -> float:
        cpu = self.client_cpu_s if which == "client" else self.server_cpu_s
        return cpu / self.seconds * 100 if self.seconds > 0 else float("nan")

    def summary(self) -> dict[str, float]:
        return {
            **asdict(self),
            "per_s": self.per_s,
            "mb_per_s": self.mb_per_s,
            "client_cpu_ms_per_1000": self.cpu_ms_per_1000("client"),
            "server_cpu_ms_per_1000": self.cpu_ms_per_1000("server"),
            "client_cpu_percent": self.cpu_percent("client"),
            "server_cpu_percent": self.cpu_percent("server"),
        }


class Window:
    """Marks taken as units complete; the figure spans the first mark (or :meth:`open`) to the one that
    reaches ``expected``.

    The first unit is left out so that a path that opens its connection with its first unit (DC's
    destinations do) is measured on its steady flow, like a baseline whose connection is open.
    """

    def __init__(self, expected: int, server_cpu: Callable[[], float]) -> None:
        self.expected = expected
        self._server_cpu = server_cpu
        self._done = 0
        self._start: tuple[float, float, float] | None = None
        self.figure = Figure()
        self.finished = threading.Event()

    def open(self) -> None:
        """Start the window before any unit: for a baseline that is one unit (a COPY)."""
        self._start = (time.perf_counter(), _client_cpu(), self._server_cpu())

    def mark(self, units: int, nbytes: int = 0) -> None:
        self._done += units
        if self._start is None:
            self.open()
            self.figure.first_unit = units
        else:
            self.figure.units += units
            self.figure.bytes += nbytes
        if self._done >= self.expected and not self.finished.is_set():
            assert self._start is not None
            wall, client, server = self._start
            self.figure.seconds = time.perf_counter() - wall
            self.figure.client_cpu_s = _client_cpu() - client
            self.figure.server_cpu_s = self._server_cpu() - server
            self.finished.set()


class _Down(Destination[None]):
    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("down while the buffer fills")


class _Timed(Destination[None]):
    """The destination under test, marking each confirmed batch; anything short of a full success is kept."""

    def __init__(self, inner: Destination[Any], window: Window, *, per_batch: bool = False) -> None:
        super().__init__(inner.context, None)
        self.inner = inner
        self.window = window
        self.per_batch = per_batch  # a unit is a batch (an S3 object) rather than a record
        self.problems: list[str] = []

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        try:
            outcome = self.inner.send(batch)
        except Exception as exc:
            self.problems.append(f"{type(exc).__name__}: {exc}")
            raise
        if outcome is not None and (outcome.retry or outcome.reject):
            self.problems.append(f"partial outcome: {outcome}")
            return outcome
        # len() of the text, not of its encoding, to add next to nothing to the path measured: the
        # records are ASCII, so characters are bytes.
        nbytes = sum(len(r.to_json()) for r in batch) + len(batch)
        self.window.mark(1 if self.per_batch else len(batch), nbytes)
        return None


# -- records and the buffer ---------------------------------------------------------------------------


def make_records(count: int) -> list[OutgoingRecord]:
    base = time.time_ns()
    records = []
    for n in range(count):
        rid = new_record_id()
        records.append(
            OutgoingRecord(rid, "/dc/measurement/system", base + n * 1_000_000, {**_DATA, "n": n, "record_id": rid})
        )
    return records


def line_bytes(record: OutgoingRecord) -> int:
    return len(record.to_json().encode("utf-8")) + 1


def _settings(folder: Path) -> DeliveryParams:
    # The fill is a tight submit() loop: the hand-off queue holds it all instead of dropping.
    return DeliveryParams(storage_path=str(folder), intake_queue_limit=10_000_000)


def fill(folder: Path, name: str, records: Sequence[OutgoingRecord]) -> None:
    """Write ``records`` into a fresh buffer for destination ``name``, which is down meanwhile."""
    pipeline = DeliveryPipeline(
        _settings(folder),
        {name: (_Down(_context(name), None), DestinationDeliveryParams(storage_total_limit_size="0"))},
        _Silent(),
    )
    pipeline.start()
    for record in records:
        pipeline.submit(name, record)
    if not pipeline.flush_intake(600.0):
        raise RuntimeError("the buffer did not commit the records within 600 s")
    pipeline.stop(0.0)


def drain(folder: Path, timed: _Timed, batch_size: int, timeout: float) -> None:
    """Deliver the buffer of ``folder`` through ``timed`` as destination_server does, until all is confirmed."""
    name = timed.context.name
    params = DestinationDeliveryParams(batch_size=batch_size, storage_total_limit_size="0")
    pipeline = DeliveryPipeline(_settings(folder), {name: (timed, params)}, RecordingLogger("dc.bench"))
    pipeline.start()
    try:
        if not timed.window.finished.wait(timeout):
            raise RuntimeError(f"{name}: not delivered within {timeout:.0f} s: {timed.problems[-3:]}")
        if timed.problems:
            raise RuntimeError(f"{name}: the destination failed during the run: {timed.problems[:3]}")
    finally:
        pipeline.stop(0.0)


# -- profiling the sender ---------------------------------------------------------------------------------


class _ProfiledSender(Sender):
    """cProfile enabled inside the sender thread: cProfile sees only the thread that enables it."""

    profile = cProfile.Profile()

    def run(self) -> None:
        self.profile.enable()
        try:
            super().run()
        finally:
            self.profile.disable()


@contextlib.contextmanager
def profiled_sender(out: Path) -> Iterator[None]:
    _ProfiledSender.profile = cProfile.Profile()
    # The pipeline builds its senders from its module's name: swapped for this drain only.
    setattr(delivery, "Sender", _ProfiledSender)  # noqa: B010
    try:
        yield
    finally:
        setattr(delivery, "Sender", Sender)  # noqa: B010
        _ProfiledSender.profile.dump_stats(str(out))
        text = io.StringIO()
        stats = pstats.Stats(_ProfiledSender.profile, stream=text).strip_dirs()
        stats.sort_stats("tottime").print_stats(25)
        stats.sort_stats("cumulative").print_stats(30)
        print(text.getvalue())
        print(f"profile of the sender thread: {out} (pstats)")


# -- PostgreSQL -------------------------------------------------------------------------------------------


class Postgres:
    def __init__(self, folder: Path) -> None:
        self.server = PostgresServer(folder)

    def __enter__(self) -> Postgres:
        self.server.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.stop()

    def connect(self) -> Any:
        import psycopg

        s = self.server.settings()
        return psycopg.connect(
            host=str(s["host"]),
            port=int(s["port"]),
            user=str(s["user"]),
            password=str(s["password"]),
            dbname=str(s["database"]),
            autocommit=True,
        )

    def cpu(self) -> float:
        pid_file = self.server.data_dir / "postmaster.pid"
        return _tree_cpu(int(pid_file.read_text().split("\n", 1)[0]))

    def create_table(self, connection: Any, table: str) -> None:
        # The shape the PgSQL destination creates: the baselines load into the same kind of table.
        connection.execute(f"CREATE TABLE {table} (tag varchar, time timestamp, data jsonb, record_id text)")
        connection.execute(f"CREATE UNIQUE INDEX {table}_record_id ON {table} (record_id)")

    def count_and_drop(self, connection: Any, table: str, expected: int) -> None:
        # Dropped at once so that autovacuum does not work on it during the next measurement.
        (count,) = connection.execute(f"SELECT count(*) FROM {table}").fetchone()
        connection.execute(f"DROP TABLE {table}")
        if count != expected:
            raise RuntimeError(f"table {table}: {count} rows, expected {expected}")


def pg_rows(tag: str, records: Sequence[OutgoingRecord]) -> list[tuple[str, dt.datetime, str, str]]:
    """The values the PgSQL destination inserts for each record (time: the stamp, UTC, naive)."""
    return [(tag, EPOCH + dt.timedelta(microseconds=r.stamp_ns // 1000), r.to_json(), r.record_id) for r in records]


def _data_bytes(rows: Sequence[tuple[str, dt.datetime, str, str]]) -> int:
    """Bytes of the rows' JSON as lines; counted before a window opens, to stay out of the path timed."""
    return sum(len(row[2].encode("utf-8")) + 1 for row in rows)


def pg_copy(pg: Postgres, table: str, rows: Sequence[tuple[str, dt.datetime, str, str]], *, binary: bool) -> Figure:
    nbytes = _data_bytes(rows)
    with pg.connect() as connection:
        pg.create_table(connection, table)
        window = Window(len(rows), pg.cpu)
        window.open()
        with (
            connection.transaction(),
            connection.cursor() as cursor,
            cursor.copy(_copy_statement(connection, table, binary=binary)) as copy,
        ):
            if binary:
                copy.set_types(_BINARY_TYPES)
            for row in rows:
                copy.write_row(row)
        window.mark(len(rows), nbytes)
        pg.count_and_drop(connection, table, len(rows))
    return window.figure


_BINARY_TYPES = ["varchar", "timestamp", "jsonb", "text"]


def _copy_statement(connection: Any, table: str, *, binary: bool) -> str:
    """COPY of the four columns; binary with the dumper the PgSQL destination registers for ``data``."""
    from dc_destinations.pgsql import json_text_binary_dumper

    if not binary:
        return f"COPY {table} (tag, time, data, record_id) FROM STDIN"
    connection.adapters.register_dumper(None, json_text_binary_dumper())
    return f"COPY {table} (tag, time, data, record_id) FROM STDIN (FORMAT BINARY)"


def pg_direct(pg: Postgres, table: str, rows: Sequence[tuple[str, dt.datetime, str, str]], batch_size: int) -> Figure:
    """The PgSQL destination's statement from memory: per batch, one binary COPY straight into the table,
    outside a transaction block (the COPY is its own transaction)."""
    with pg.connect() as connection:
        pg.create_table(connection, table)
        statement = _copy_statement(connection, table, binary=True)
        batches = [rows[start : start + batch_size] for start in range(0, len(rows), batch_size)]
        sizes = [_data_bytes(batch) for batch in batches]
        window = Window(len(rows), pg.cpu)
        for batch, nbytes in zip(batches, sizes, strict=True):
            with connection.cursor() as cursor, cursor.copy(statement) as copy:
                copy.set_types(_BINARY_TYPES)
                for row in batch:
                    copy.write_row(row)
            window.mark(len(batch), nbytes)
        pg.count_and_drop(connection, table, len(rows))
    return window.figure


def pg_insert(pg: Postgres, table: str, rows: Sequence[tuple[str, dt.datetime, str, str]], batch_size: int) -> Figure:
    """The statement PgSQL used before COPY (still its fallback), one transaction per batch, from rows in memory."""
    insert = (
        f"INSERT INTO {table} (tag, time, data, record_id) VALUES (%s, %s, %s::jsonb, %s)"
        " ON CONFLICT (record_id) DO NOTHING"
    )
    with pg.connect() as connection:
        pg.create_table(connection, table)
        batches = [rows[start : start + batch_size] for start in range(0, len(rows), batch_size)]
        sizes = [_data_bytes(batch) for batch in batches]
        window = Window(len(rows), pg.cpu)
        for batch, nbytes in zip(batches, sizes, strict=True):
            with connection.transaction(), connection.cursor() as cursor:
                cursor.executemany(insert, batch)
            window.mark(len(batch), nbytes)
        pg.count_and_drop(connection, table, len(rows))
    return window.figure


def pg_staged(pg: Postgres, table: str, rows: Sequence[tuple[str, dt.datetime, str, str]], batch_size: int) -> Figure:
    """The PgSQL destination's statements from memory when a record of the batch is in the table already:
    per batch, COPY into a temporary table emptied at commit, then INSERT … SELECT … ON CONFLICT DO
    NOTHING."""
    with pg.connect() as connection:
        pg.create_table(connection, table)
        connection.execute(f"CREATE TEMP TABLE staging (LIKE {table}) ON COMMIT DELETE ROWS")
        batches = [rows[start : start + batch_size] for start in range(0, len(rows), batch_size)]
        sizes = [_data_bytes(batch) for batch in batches]
        window = Window(len(rows), pg.cpu)
        for batch, nbytes in zip(batches, sizes, strict=True):
            with connection.transaction(), connection.cursor() as cursor:
                with cursor.copy("COPY staging (tag, time, data, record_id) FROM STDIN") as copy:
                    for row in batch:
                        copy.write_row(row)
                cursor.execute(f"INSERT INTO {table} SELECT * FROM staging ON CONFLICT (record_id) DO NOTHING")
            window.mark(len(batch), nbytes)
        pg.count_and_drop(connection, table, len(rows))
    return window.figure


class _Discard(Destination[None]):
    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        pass


def discard_drain(folder: Path, records: Sequence[OutgoingRecord], batch_size: int) -> Figure:
    """The buffer and sender alone: a destination that confirms at once (no server, no CPU of one)."""
    name = "bench"
    fill(folder, name, records)
    timed = _Timed(_Discard(_context(name), None), Window(len(records), lambda: 0.0))
    drain(folder, timed, batch_size, timeout=max(300.0, len(records) / 200))
    return timed.window.figure


def pg_dc(
    pg: Postgres, folder: Path, table: str, records: Sequence[OutgoingRecord], batch_size: int, profile: Path | None
) -> Figure:
    from dc_destinations.pgsql import PgSQL, PgSQLParams

    name = "bench"
    fill(folder, name, records)
    settings = {**pg.server.settings(), "table": table}
    plugin = PgSQL(_context(name), parse_params(PgSQLParams, settings, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    timed = _Timed(plugin, Window(len(records), pg.cpu))
    try:
        with profiled_sender(profile) if profile else contextlib.nullcontext():
            drain(folder, timed, batch_size, timeout=max(300.0, len(records) / 200))
    finally:
        plugin.on_deactivate()
    with pg.connect() as connection:
        pg.count_and_drop(connection, table, len(records))
    return timed.window.figure


def run_pgsql(
    pg: Postgres, scratch: Path, run: int, records: Sequence[OutgoingRecord], batch_sizes: Sequence[int], profile: bool
) -> dict[str, Figure]:
    rows = pg_rows("bench", records)
    out = {"copy": pg_copy(pg, f"copy_{run}", rows, binary=False)}
    _say(run, LABELS["copy"], out["copy"], "rows")
    out["copybinary"] = pg_copy(pg, f"copybinary_{run}", rows, binary=True)
    _say(run, LABELS["copybinary"], out["copybinary"], "rows")
    for size in batch_sizes:
        key = f"direct_{size}"
        out[key] = pg_direct(pg, f"{key}_{run}", rows, size)
        _say(run, _label(key), out[key], "rows")
        key = f"insert_{size}"
        out[key] = pg_insert(pg, f"{key}_{run}", rows, size)
        _say(run, _label(key), out[key], "rows")
        key = f"staged_{size}"
        out[key] = pg_staged(pg, f"{key}_{run}", rows, size)
        _say(run, _label(key), out[key], "rows")
        folder = scratch / f"discard-{run}-{size}"
        folder.mkdir()
        key = f"discard_{size}"
        out[key] = discard_drain(folder, records, size)
        shutil.rmtree(folder)
        _say(run, _label(key), out[key], "rows")
        folder = scratch / f"pg-{run}-{size}"
        folder.mkdir()
        profile_to = Path(tempfile.gettempdir()) / f"dc_storage_pgsql_{size}.pstats" if profile and run == 0 else None
        key = f"dc_{size}"
        out[key] = pg_dc(pg, folder, f"dc_{size}_{run}", records, size, profile_to)
        shutil.rmtree(folder)
        _say(run, _label(key, "PgSQL"), out[key], "rows")
    return out


# -- S3 records -------------------------------------------------------------------------------------------


class Seaweed:
    def __init__(self, folder: Path) -> None:
        self.server = SeaweedS3Server(folder)

    def __enter__(self) -> Seaweed:
        self.server.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.stop()

    def cpu(self) -> float:
        return _tree_cpu(int((self.server.state_dir / "weed.pid").read_text().strip()))

    def count(self, prefix: str) -> int:
        client = self.server.client()
        pages = client.get_paginator("list_objects_v2").paginate(Bucket=self.server.bucket, Prefix=prefix)
        return sum(len(page.get("Contents", [])) for page in pages)


def s3_put(s3: Seaweed, prefix: str, records: Sequence[OutgoingRecord], batch_size: int) -> Figure:
    """The same JSON lines cut into the same objects, one put_object each, from bytes in memory."""
    bodies = [
        b"".join((r.to_json() + "\n").encode("utf-8") for r in records[start : start + batch_size])
        for start in range(0, len(records), batch_size)
    ]
    client = s3.server.client(timeout=60.0)
    window = Window(len(bodies), s3.cpu)
    for n, body in enumerate(bodies):
        client.put_object(
            Bucket=s3.server.bucket, Key=f"{prefix}{n:06d}", Body=body, ContentType="application/x-ndjson"
        )
        window.mark(1, len(body))
    client.close()
    if s3.count(prefix) != len(bodies):
        raise RuntimeError(f"{prefix}: {s3.count(prefix)} objects, expected {len(bodies)}")
    return window.figure


def s3_dc(s3: Seaweed, folder: Path, prefix: str, records: Sequence[OutgoingRecord], batch_size: int) -> Figure:
    from dc_destinations.s3 import S3, S3Params

    name = "bench"
    fill(folder, name, records)
    settings = {**s3.server.settings(), "s3_key_format": f"/{prefix}$UUID", "timeout": 60.0}
    plugin = S3(_context(name), parse_params(S3Params, settings, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    objects = -(-len(records) // batch_size)
    # One send() is one object: total_file_size (100M) is far above a batch of these records.
    timed = _Timed(plugin, Window(objects, s3.cpu), per_batch=True)
    try:
        drain(folder, timed, batch_size, timeout=max(300.0, len(records) / 200))
    finally:
        plugin.on_deactivate()
        plugin.on_cleanup()
    if s3.count(prefix) != objects:
        raise RuntimeError(f"{prefix}: {s3.count(prefix)} objects, expected {objects}")
    return timed.window.figure


def run_s3(
    s3: Seaweed, scratch: Path, run: int, records: Sequence[OutgoingRecord], batch_sizes: Sequence[int]
) -> dict[str, Figure]:
    out: dict[str, Figure] = {}
    for size in batch_sizes:
        key = f"put_{size}"
        out[key] = s3_put(s3, f"put/{run}/{size}/", records, size)
        _say(run, _label(key), out[key], "objects")
        folder = scratch / f"s3-{run}-{size}"
        folder.mkdir()
        key = f"dc_{size}"
        out[key] = s3_dc(s3, folder, f"dc/{run}/{size}/", records, size)
        shutil.rmtree(folder)
        _say(run, _label(key, "S3"), out[key], "objects")
    return out


# -- file upload -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FileSet:
    kind: str  # "small" or "large"
    paths: list[Path]

    @property
    def bytes(self) -> int:
        return sum(path.stat().st_size for path in self.paths)


def make_files(folder: Path, kind: str, count: int, size: int) -> FileSet:
    """Random bytes, which compress no better than camera images or maps do."""
    folder.mkdir(parents=True)
    paths = []
    for n in range(count):
        path = folder / f"{kind}-{n:04d}.jpg"
        with path.open("wb") as out:
            for start in range(0, size, 2**20):
                out.write(os.urandom(min(2**20, size - start)))
        paths.append(path)
    return FileSet(kind, paths)


def file_records(files: FileSet, prefix: str) -> list[OutgoingRecord]:
    """Records naming one file each, as a file-saving measurement's records do (src_fields / upload_fields)."""
    base = time.time_ns()
    records = []
    for n, path in enumerate(files.paths):
        rid = new_record_id()
        data = {
            "name": "camera",
            "local_paths": {"image": str(path)},
            "remote_paths": {"minio": {"image": f"{prefix}{path.name}"}},
            "record_id": rid,
        }
        records.append(OutgoingRecord(rid, "/dc/measurement/camera", base + n * 1_000_000, data))
    return records


def files_dc(s3: Seaweed, files: FileSet, prefix: str, batch_size: int) -> Figure:
    """The MinIO destination's send() of the records naming the files, batch after batch, as its sender calls it."""
    from dc_destinations.minio import MinIO, MinIOParams

    server = s3.server
    settings = {
        "endpoint": server.endpoint,
        "access_key_id": server.access_key,
        "secret_access_key": server.secret_key,
        "bucket": server.bucket,
        "src_fields": ["local_paths.image"],
        "upload_fields": ["remote_paths.minio.image"],
        "timeout": 120.0,
    }
    plugin = MinIO(_context("files"), parse_params(MinIOParams, settings, "destination_server.files"))
    plugin.on_configure()
    plugin.on_activate()
    records = file_records(files, prefix)
    window = Window(len(records), s3.cpu)
    try:
        window.open()
        for start in range(0, len(records), batch_size):
            batch = records[start : start + batch_size]
            outcome = plugin.send(batch)
            if outcome is not None and (outcome.retry or outcome.reject):
                raise RuntimeError(f"MinIO destination: not every file was confirmed: {outcome}")
            window.mark(len(batch), sum(Path(r.data["local_paths"]["image"]).stat().st_size for r in batch))
    finally:
        plugin.on_deactivate()
        plugin.on_cleanup()
    if s3.count(prefix) != len(records):
        raise RuntimeError(f"{prefix}: {s3.count(prefix)} objects, expected {len(records)}")
    return window.figure


def files_boto3(s3: Seaweed, files: FileSet, prefix: str) -> Figure:
    """boto3's own upload_file with its default transfer settings (multipart and threads above 8 MB)."""
    client = s3.server.client(timeout=120.0)
    window = Window(len(files.paths), s3.cpu)
    window.open()
    for path in files.paths:
        client.upload_file(str(path), s3.server.bucket, f"{prefix}{path.name}")
        window.mark(1, path.stat().st_size)
    client.close()
    if s3.count(prefix) != len(files.paths):
        raise RuntimeError(f"{prefix}: {s3.count(prefix)} objects, expected {len(files.paths)}")
    return window.figure


def run_files(s3: Seaweed, run: int, sets: Sequence[FileSet], batch_size: int) -> dict[str, Figure]:
    measured: dict[str, Figure] = {}
    for files in sets:
        measures: list[tuple[str, Callable[[], Figure]]] = [
            (f"upload_{files.kind}", functools.partial(files_boto3, s3, files, f"boto3/{run}/{files.kind}/")),
            (f"minio_{files.kind}", functools.partial(files_dc, s3, files, f"minio/{run}/{files.kind}/", batch_size)),
        ]
        # Taking turns at going first: the page cache and the store's state favour neither side.
        for key, measure in measures if run % 2 == 0 else measures[::-1]:
            measured[key] = measure()
            _say(run, _label(key), measured[key], "files")
    return {key: measured[key] for files in sets for key in (f"upload_{files.kind}", f"minio_{files.kind}")}


# -- report -------------------------------------------------------------------------------------------------

LABELS = {
    "copy": "COPY FROM STDIN, one transaction (baseline)",
    "copybinary": "COPY FROM STDIN binary, one transaction",
    "direct": "binary COPY straight into the table, {n}/transaction",
    "insert": "INSERT … ON CONFLICT, {n} rows/transaction, no buffer",
    "staged": "COPY to temp table + INSERT … SELECT, {n}/transaction",
    "discard": "DC buffer → destination that discards, batch_size {n}",
    "dc": "DC buffer → {destination}, batch_size {n}",
    "put": "boto3 put_object, {n} records/object (baseline)",
    "upload": "boto3 upload_file, {n} files (baseline)",
    "minio": "MinIO destination send(), {n} files",
}


def _label(key: str, destination: str = "") -> str:
    kind, _, size = key.partition("_")
    return LABELS[kind].format(n=size, destination=destination)


def _say(run: int, what: str, figure: Figure, unit: str) -> None:
    print(
        f"run {run + 1}: {what}: {figure.per_s:,.0f} {unit}/s, {figure.mb_per_s:.1f} MB/s "
        f"(client {figure.client_cpu_s:.2f} s CPU, server {figure.server_cpu_s:.2f} s CPU in {figure.seconds:.2f} s)",
        flush=True,
    )


def _median(figures: Sequence[Figure], attribute: Callable[[Figure], float]) -> float:
    return statistics.median(attribute(f) for f in figures)


def _ratio(runs: Sequence[dict[str, Figure]], top: str, bottom: str, attribute: Callable[[Figure], float]) -> float:
    """Median over runs of top/bottom taken within each run."""
    return statistics.median(
        attribute(r[top]) / attribute(r[bottom]) if attribute(r[bottom]) else float("nan") for r in runs
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--records", type=int, default=100_000)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--only", default=",".join(PARTS), help="comma-separated parts: " + ", ".join(PARTS))
    parser.add_argument(
        "--batch-sizes", default=f"{DEFAULT_BATCH},5000", help="batch_size of the destinations (the first: default)"
    )
    parser.add_argument("--small-files", type=int, default=200, help="files part: how many small files")
    parser.add_argument("--small-kb", type=int, default=100, help="files part: size of a small file, KiB")
    parser.add_argument("--large-files", type=int, default=4, help="files part: how many large files")
    parser.add_argument("--large-mb", type=int, default=32, help="files part: size of a large file, MiB")
    parser.add_argument("--label", default="", help="end of the JSON file's name (default: the parts run)")
    parser.add_argument("--profile", action="store_true", help="cProfile the sender thread of the first PgSQL drains")
    args = parser.parse_args()
    parts = [p.strip() for p in args.only.split(",") if p.strip()]
    unknown = set(parts) - set(PARTS)
    if unknown:
        parser.error(f"unknown part(s) {sorted(unknown)}; choose among {', '.join(PARTS)}")
    batch_sizes = [int(b) for b in args.batch_sizes.split(",")]
    started = dt.datetime.now(dt.UTC)
    label = args.label or "_".join(parts)
    out_json = REPO / "benchmarks" / "results" / f"storage_{started:%Y-%m-%d}_{label}.json"
    print(
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at start, Python {platform.python_version()}; "
        f"{args.records:,} records of ~{line_bytes(make_records(1)[0]) - 1} bytes, {args.runs} run(s)",
        flush=True,
    )
    results: dict[str, list[dict[str, Figure]]] = {p: [] for p in parts}
    # Under /tmp: as root, PostgreSQL runs as user postgres, who must be able to enter its folder.
    scratch_root = Path(tempfile.mkdtemp(prefix="dc-storage-bench-"))
    os.chmod(scratch_root, 0o755)
    try:
        with contextlib.ExitStack() as servers:
            pg = servers.enter_context(Postgres(scratch_root / "pg")) if "pgsql" in parts else None
            s3 = servers.enter_context(Seaweed(scratch_root / "s3")) if "s3" in parts or "files" in parts else None
            file_sets: list[FileSet] = []
            if "files" in parts:
                file_sets = [
                    make_files(scratch_root / "files" / "small", "small", args.small_files, args.small_kb * 2**10),
                    make_files(scratch_root / "files" / "large", "large", args.large_files, args.large_mb * 2**20),
                ]
                # Older than the MinIO destination's complete_after (1 s by default), or it waits for them.
                time.sleep(1.5)
            for run in range(args.runs):
                scratch = scratch_root / f"run-{run}"
                scratch.mkdir()
                records = make_records(args.records)
                # Out of the cyclic collector's sight: destination_server holds a batch, not the whole
                # backlog, and the collector traversing it made the larger batches look slower.
                gc.freeze()
                if pg is not None:
                    results["pgsql"].append(run_pgsql(pg, scratch, run, records, batch_sizes, args.profile))
                if s3 is not None and "s3" in parts:
                    results["s3"].append(run_s3(s3, scratch, run, records, batch_sizes))
                if s3 is not None and file_sets:
                    results["files"].append(run_files(s3, run, file_sets, batch_sizes[0]))
                shutil.rmtree(scratch)
                del records
                gc.unfreeze()
                gc.collect()
    finally:
        shutil.rmtree(scratch_root, ignore_errors=True)
    report(results, args, batch_sizes, started, out_json)


def _code_state() -> dict[str, Any]:
    """Which DC code was measured: the commit, and the files of the delivery path changed since."""

    def git(*argv: str) -> str:
        done = subprocess.run(["git", *argv], cwd=REPO, capture_output=True, text=True, check=False)
        return done.stdout

    # Not stripped: a porcelain line starts with its two status columns, the first often a space.
    changed = git("status", "--porcelain", "--", "dc_destinations", "dc_core").splitlines()
    return {"commit": git("rev-parse", "HEAD").strip(), "changed": [line[3:] for line in changed]}


def report(
    results: dict[str, list[dict[str, Figure]]],
    args: argparse.Namespace,
    batch_sizes: Sequence[int],
    started: dt.datetime,
    out_json: Path,
) -> None:
    runs = args.runs
    print(f"\nmedians of {runs} run(s); ratios taken within each run; CPU over the same window as the rate")
    header = f"  {'path':<56} {'units/s':>9} {'MB/s':>6} {'client CPU':>10} {'server CPU':>10} {'vs baseline':>11}"
    print("CPU: % of one core over the window (2 cores = 200 %); the server's CPU is its whole process tree")
    medians: dict[str, dict[str, dict[str, float]]] = {}
    for part, unit, destination in (("pgsql", "rows", "PgSQL"), ("s3", "objects", "S3"), ("files", "files", "")):
        part_runs = results.get(part)
        if not part_runs:
            continue
        print(f"\n{part} (units: {unit})\n{header}")
        medians[part] = {}
        for key in part_runs[0]:
            figures = [r[key] for r in part_runs]
            base = {"pgsql": "copy", "s3": "put_", "files": "upload_"}[part]
            if part != "pgsql":
                base += key.rsplit("_", 1)[-1]
            row = {
                "per_s": _median(figures, lambda f: f.per_s),
                "mb_per_s": _median(figures, lambda f: f.mb_per_s),
                "client_cpu_ms_per_1000": _median(figures, lambda f: f.cpu_ms_per_1000("client")),
                "server_cpu_ms_per_1000": _median(figures, lambda f: f.cpu_ms_per_1000("server")),
                "client_cpu_percent": _median(figures, lambda f: f.cpu_percent("client")),
                "server_cpu_percent": _median(figures, lambda f: f.cpu_percent("server")),
            }
            vs = "baseline"
            if key != base:
                row["ratio_to_" + base] = _ratio(part_runs, key, base, lambda f: f.per_s)
                vs = f"{row['ratio_to_' + base]:.0%}"
            medians[part][key] = row
            server = f"{row['server_cpu_percent']:>9.0f}%" if not key.startswith("discard") else f"{'—':>10}"
            print(
                f"  {_label(key, destination):<56} {row['per_s']:>9,.0f} {row['mb_per_s']:>6.1f} "
                f"{row['client_cpu_percent']:>9.0f}% {server} {vs:>11}"
            )
    document = {
        "date": started.isoformat(timespec="seconds"),
        "machine": {
            "cpus": os.cpu_count(),
            "load_average_at_end": os.getloadavg(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "argv": sys.argv[1:],
        "code": _code_state(),
        "records": args.records,
        "record_bytes": line_bytes(make_records(1)[0]) - 1,
        "runs": runs,
        "batch_sizes": list(batch_sizes),
        "files": {
            "small": [args.small_files, args.small_kb * 2**10],
            "large": [args.large_files, args.large_mb * 2**20],
        },
        "medians": medians,
        "per_run": {part: [{k: f.summary() for k, f in r.items()} for r in rs] for part, rs in results.items()},
    }
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nJSON: {out_json}")


if __name__ == "__main__":
    main()
