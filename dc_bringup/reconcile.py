"""``dc reconcile``: what the bucket, the records table and files_metrics disagree on, for one robot and a time range.

The three stores are written by independent destinations (MinIO uploads the file, PgSQL writes the
record, FilesMetrics the file's row), so a record dead-lettered by one of them leaves the others
alone. Three kinds of orphans are listed:

* ``objects_without_row``: objects of the robot (their ``x-amz-meta-dc-robot-name``) whose
  ``x-amz-meta-dc-record-id`` is in no row of the records table and whose key is in no row of
  either table;
* ``rows_without_object``: object keys a record names under ``remote_paths`` that the bucket lacks;
* ``uploaded_but_missing``: files_metrics rows marked ``uploaded`` whose object the bucket lacks.

``--repair`` changes one thing: the ``uploaded_but_missing`` rows are set ``uploaded = false``
(``verified_at`` cleared, ``updated_at`` now), so that files_metrics stops telling a team (and a
retention job) that the bucket holds the file. Nothing is deleted or uploaded: an orphan object or a
row without its object is only listed, for a person to decide.

An object's time is its record id's (a UUIDv7 holds the millisecond DC received the record), else
its upload time; a row's is its ``time`` (records) or ``timestamp`` (files_metrics), both UTC.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import sys
import urllib.parse
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

_REMOTE_PATHS = "remote_paths"


@dataclass
class Report:
    robot: str
    since: dt.datetime
    until: dt.datetime
    objects_without_row: list[dict[str, str]] = field(default_factory=list)
    rows_without_object: list[dict[str, str]] = field(default_factory=list)
    uploaded_but_missing: list[dict[str, str]] = field(default_factory=list)
    repaired: int = 0
    checked: dict[str, int] = field(default_factory=dict)

    @property
    def orphans(self) -> int:
        return len(self.objects_without_row) + len(self.rows_without_object) + len(self.uploaded_but_missing)

    def as_json(self) -> dict[str, Any]:
        return {
            "robot": self.robot,
            "since": self.since.isoformat(),
            "until": self.until.isoformat(),
            "checked": self.checked,
            "objects_without_row": self.objects_without_row,
            "rows_without_object": self.rows_without_object,
            "uploaded_but_missing": self.uploaded_but_missing,
            "repaired": self.repaired,
        }


def named_keys(data: Any, storage: str | None) -> Iterator[str]:
    """The object keys a record names: every text under its ``remote_paths`` (of ``storage`` alone when
    given), wherever the measurement's ``nested`` put it."""
    if isinstance(data, Mapping):
        for key, value in data.items():
            if key == _REMOTE_PATHS and isinstance(value, Mapping):
                for name, paths in value.items():
                    if storage is None or name == storage:
                        yield from _texts(paths)
            else:
                yield from named_keys(value, storage)
    elif isinstance(data, list):
        for item in data:
            yield from named_keys(item, storage)


def _texts(value: Any) -> Iterator[str]:
    if isinstance(value, str):
        if value:
            yield value.removeprefix("/")
    elif isinstance(value, Mapping):
        for inner in value.values():
            yield from _texts(inner)
    elif isinstance(value, list):
        for inner in value:
            yield from _texts(inner)


def _object_key(remote_path: str, bucket: str) -> str | None:
    """The key of a files_metrics ``remote_path`` in ``bucket`` (an ``s3://bucket/key`` URI or a key);
    None when it names another bucket."""
    if remote_path.startswith("s3://"):
        named_bucket, _, key = remote_path[5:].partition("/")
        return key if named_bucket == bucket else None
    return remote_path.removeprefix("/")


def record_time(record_id: str) -> dt.datetime | None:
    """The time a UUIDv7 record id holds, None for any other id."""
    try:
        parsed = uuid.UUID(record_id)
    except ValueError:
        return None
    if parsed.version != 7:
        return None
    return dt.datetime.fromtimestamp((parsed.int >> 80) / 1000, dt.UTC)


def reconcile(
    connection: Any,
    s3: Any,
    bucket: str,
    robot: str,
    since: dt.datetime,
    until: dt.datetime,
    *,
    table: str = "dc",
    files_table: str = "files_metrics",
    prefix: str = "",
    storage: str | None = None,
    repair: bool = False,
) -> Report:
    """Compare the stores (``connection``: psycopg, ``s3``: a boto3 client) and optionally repair."""
    from psycopg import sql

    # Here, not at the top: `dc --help` builds this command's parser without the aws extra.
    from dc_destinations.object_files import RECORD_ID_METADATA, ROBOT_NAME_METADATA, stored_object

    report = Report(robot, since, until)
    connection.execute("SET TIME ZONE 'UTC'")  # a timestamp without zone is UTC in DC's tables
    window = {"robot": robot, "since": since, "until": until}
    records = connection.execute(_records_query(connection, table), window).fetchall()
    record_ids = {str(rid) for rid, _ in records if rid}
    named: dict[str, str] = {}  # key -> record id naming it
    for rid, data in records:
        for key in named_keys(data, storage):
            named.setdefault(key, str(rid))
    # A robot without FilesMetrics has no such table: nothing to compare on that side.
    has_files = connection.execute("SELECT to_regclass(%s) IS NOT NULL", (files_table,)).fetchone()[0]
    files = (
        connection.execute(
            sql.SQL(
                "SELECT id, remote_path, uploaded, record_id FROM {} WHERE robot_name = %(robot)s "
                "AND timestamp >= %(since)s AND timestamp < %(until)s AND (bucket IS NULL OR bucket = %(bucket)s)"
            ).format(sql.Identifier(*files_table.split("."))),
            {**window, "bucket": bucket},
        ).fetchall()
        if has_files
        else []
    )
    file_keys: dict[str, tuple[Any, bool, str]] = {}
    for row_id, remote_path, uploaded, row_record in files:
        file_key = _object_key(str(remote_path), bucket)
        if file_key:
            file_keys[file_key] = (row_id, bool(uploaded), str(row_record or ""))

    stored: dict[str, dict[str, str]] = {}  # key -> its dc-* metadata, for the objects listed
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        for item in page.get("Contents", []):
            key = item["Key"]
            metadata = s3.head_object(Bucket=bucket, Key=key).get("Metadata", {})
            stored[key] = {name: urllib.parse.unquote(value) for name, value in metadata.items()}
            owner = stored[key].get(ROBOT_NAME_METADATA)
            if owner != robot or key in named or key in file_keys:
                continue
            rid = stored[key].get(RECORD_ID_METADATA, "")
            when = record_time(rid) or item["LastModified"]
            if since <= when < until and rid not in record_ids:
                report.objects_without_row.append({"key": key, "record_id": rid})

    def exists(key: str) -> bool:
        if key in stored:
            return True
        if key.startswith(prefix):
            return False  # listed above: not there
        return stored_object(s3, bucket, key) is not None

    for key, rid in sorted(named.items()):
        if not exists(key):
            report.rows_without_object.append({"key": key, "record_id": rid, "table": table})
    missing_ids = []
    for key, (row_id, uploaded, rid) in sorted(file_keys.items()):
        if uploaded and not exists(key):
            report.uploaded_but_missing.append({"key": key, "record_id": rid, "table": files_table})
            missing_ids.append(row_id)
    if repair and missing_ids:
        cursor = connection.execute(
            sql.SQL(
                "UPDATE {} SET uploaded = false, verified_at = NULL, updated_at = (now() AT TIME ZONE 'UTC') "
                "WHERE id = ANY(%(ids)s) AND uploaded"
            ).format(sql.Identifier(*files_table.split("."))),
            {"ids": missing_ids},
        )
        report.repaired = cursor.rowcount
        connection.commit()
    report.checked = {"records": len(records), "files_metrics_rows": len(files), "objects": len(stored)}
    return report


# A table DC made (typed columns, its unique btree beginning (robot_name, name, time)): the robot's
# record names by skipping through that index, then a seek per name into the range. Reading the
# range's rows of every robot and keeping one robot's (the original's shape has no robot column)
# grows with the fleet: 1 M rows for an hour of 100 robots of the robot job.
_TYPED_RECORDS = """
WITH RECURSIVE names(name) AS (
    (SELECT name FROM {t} WHERE robot_name = %(robot)s AND name IS NOT NULL ORDER BY name LIMIT 1)
    UNION ALL
    SELECT (SELECT name FROM {t} WHERE robot_name = %(robot)s AND name > names.name ORDER BY name LIMIT 1)
    FROM names WHERE names.name IS NOT NULL
)
SELECT r.record_id, r.data FROM names CROSS JOIN LATERAL (
    SELECT record_id, data FROM {t}
    WHERE robot_name = %(robot)s AND name = names.name AND time >= %(since)s AND time < %(until)s) AS r
UNION ALL
SELECT record_id, data FROM {t}
WHERE robot_name = %(robot)s AND name IS NULL AND time >= %(since)s AND time < %(until)s"""


def _records_query(connection: Any, table: str) -> Any:
    """The records of %(robot)s in [%(since)s, %(until)s): through the typed columns' index in a table DC
    made (robot_name is the record's top-level one there too), else from ``data``."""
    from psycopg import sql

    from dc_destinations.pgsql.table import read_shape

    identifier = sql.Identifier(*table.split("."))
    shape = read_shape(connection, identifier)
    if shape is not None and shape.typed:
        return sql.SQL(_TYPED_RECORDS).format(t=identifier)
    return sql.SQL(
        "SELECT record_id, data FROM {} WHERE time >= %(since)s AND time < %(until)s"
        " AND data->>'robot_name' = %(robot)s"
    ).format(identifier)


def _when(text: str) -> dt.datetime:
    """An ISO 8601 time; without a zone, UTC."""
    value = dt.datetime.fromisoformat(text)
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


_when.__name__ = "ISO 8601 time"  # argparse names the type in its error: "invalid ISO 8601 time value: …"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from dc_dashboard.cli import add_store_arguments

    p.add_argument("--robot", required=True, help="the robot's name (robot_name in records and files_metrics)")
    p.add_argument("--since", required=True, type=_when, help="start of the range, ISO 8601 (UTC without a zone)")
    p.add_argument("--until", type=_when, help="end of the range, excluded (default: now)")
    p.add_argument("--prefix", default="", help="list only the objects under this key prefix (fewer requests)")
    p.add_argument("--storage", help="only the keys a record names under remote_paths.<storage> (default: all)")
    p.add_argument(
        "--repair", action="store_true", help="set uploaded = false on files_metrics rows whose object is missing"
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    add_store_arguments(p)


def run(args: argparse.Namespace) -> int:
    """0: the stores agree; 1: orphans listed; 2: the stores could not be read."""
    try:
        import psycopg
    except ImportError:
        print('dc reconcile: psycopg is not installed (pip install "ros2-dc[pgsql,aws]")', file=sys.stderr)
        return 2
    from dc_dashboard.settings import from_sources
    from dc_destinations.object_files import ObjectStoreParams

    settings = from_sources(args)
    if not settings.s3.configured:
        print("dc reconcile: no bucket (--s3-bucket or DC_S3_BUCKET)", file=sys.stderr)
        return 2
    until = args.until or dt.datetime.now(dt.UTC)
    store = ObjectStoreParams(
        endpoint=settings.s3.endpoint,
        access_key_id=settings.s3.access_key_id,
        secret_access_key=settings.s3.secret_access_key,
        bucket=settings.s3.bucket,
        region=settings.s3.region,
    )
    s3 = store.client(logging.getLogger("dc.reconcile"), "dc reconcile")
    try:
        with psycopg.connect(**settings.postgres.connect_kwargs()) as connection:
            report = reconcile(
                connection,
                s3,
                settings.s3.bucket,
                args.robot,
                args.since,
                until,
                table=settings.postgres.table,
                files_table=settings.postgres.files_table,
                prefix=args.prefix,
                storage=args.storage,
                repair=args.repair,
            )
    except Exception as exc:  # psycopg's and botocore's many types: each means the stores could not be read
        print(f"dc reconcile: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report.as_json(), indent=2))
    else:
        _print(report, settings.postgres.address(), settings.s3.bucket)
    return 1 if report.orphans else 0


def _print(report: Report, database: str, bucket: str) -> None:
    c = report.checked
    print(
        f"robot {report.robot}, {report.since.isoformat()} to {report.until.isoformat()}: "
        f"{c['records']} records, {c['files_metrics_rows']} files_metrics rows ({database}), "
        f"{c['objects']} objects (bucket {bucket})"
    )
    sections = (
        ("objects without a row", report.objects_without_row),
        ("rows naming an object the bucket lacks", report.rows_without_object),
        ("files marked uploaded but missing", report.uploaded_but_missing),
    )
    for title, items in sections:
        print(f"{title}: {len(items)}")
        for item in items:
            print(f"  {item['key']}  record {item['record_id'] or '?'}")
    if report.repaired:
        print(f"repaired: {report.repaired} files_metrics rows set uploaded = false")
