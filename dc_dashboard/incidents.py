"""The Incidents page: what the Recorder (dc_measurements/Recorder) stored, and its MCAP files through the dashboard.

An incident is found by its record's shape (``triggers``, ``topics``, ``cut_by_memory_bound``:
dc_dashboard.catalog), whatever the measurement was named. The list follows the shared filters (robot, run,
time range), a reason's text and a topic's name (one with messages in the file); each row links to its file,
which the dashboard fetches from the bucket and passes on (the browser never sees a key's signature), only
for a ``.mcap`` key whose bytes are an MCAP file.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Generator
from dataclasses import dataclass
from html import escape
from typing import Any
from urllib.parse import quote

from dc_dashboard.errors import DashboardError
from dc_dashboard.filters import Filters
from dc_dashboard.objects import ImageStore, _reason
from dc_dashboard.pages import NONE, _page_form, _size, stat, when
from dc_dashboard.queries import Store, _remote_key

PAGE = 50
MCAP_MAGIC = b"\x89MCAP0\r\n"
CHUNK = 1024 * 1024


@dataclass(frozen=True)
class Incident:
    time: dt.datetime
    robot: str
    run: str
    name: str
    start: float
    end: float
    reasons: list[str]
    # (topic, messages, bytes, absent, lost: to the memory bound, in transport)
    topics: list[tuple[str, int, int, bool, int, int]]
    size: int
    cut: bool
    key: str


def _topic(entry: dict[str, Any], number: Any) -> tuple[str, int, int, bool, int, int]:
    return (
        str(entry.get("topic", "")),
        int(number(entry.get("messages"))),
        int(number(entry.get("bytes"))),
        (entry.get("absent") is True),
        int(number(entry.get("lost_to_memory_bound"))),
        int(number(entry.get("lost_in_transport"))),
    )


def _lost(bound: int, transport: int) -> str:
    said = [f"{bound:,} let go by the memory bound"] if bound else []
    said += [f"{transport:,} lost in transport"] if transport else []
    return ", " + ", ".join(said) if said else ""


def _incident(name: str, when_: dt.datetime, robot: str, run: str, record: dict[str, Any]) -> Incident:
    def number(value: Any) -> float:
        return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else 0.0

    triggers = record.get("triggers")
    triggers = triggers if isinstance(triggers, list) else []
    topics = record.get("topics")
    topics = topics if isinstance(topics, list) else []
    return Incident(
        time=when_,
        robot=robot or str(record.get("robot_name", "")),
        run=run or str(record.get("run_id", "")),
        name=name,
        start=number(record.get("start")),
        end=number(record.get("end")),
        reasons=[str(t.get("reason", "")) for t in triggers if isinstance(t, dict)][:20],
        topics=[_topic(t, number) for t in topics if isinstance(t, dict)][:50],
        size=int(number(record.get("size"))),
        cut=record.get("cut_by_memory_bound") is True,
        key=_remote_key(record, "mcap"),
    )


def incidents(store: Store, connection: Any, filters: Filters) -> tuple[list[Incident], bool]:
    """The newest incidents of the filters (before ``filters.before``, a reason holding ``filters.reason``, a
    topic with messages in the file whose name holds ``filters.topic``)."""
    from psycopg import sql

    conditions = []
    if filters.reason:  # any trigger whose reason holds the text, any case
        conditions.append(
            sql.SQL(
                "EXISTS (SELECT 1 FROM jsonb_array_elements(data #> %(p)s -> 'triggers') AS t(v)"
                " WHERE (t.v ->> 'reason') ILIKE %(text)s ESCAPE '\\')"
            )
        )
    if filters.topic:  # a topic the file holds messages of (not one recorded as absent or silent)
        conditions.append(
            sql.SQL(
                "EXISTS (SELECT 1 FROM jsonb_array_elements(data #> %(p)s -> 'topics') AS s(v)"
                " WHERE (s.v ->> 'topic') ILIKE %(topic)s ESCAPE '\\'"
                " AND jsonb_typeof(s.v -> 'messages') = 'number' AND (s.v ->> 'messages')::numeric > 0)"
            )
        )
    condition = sql.SQL(" AND ").join(conditions) if conditions else None
    rows = store.newest(connection, filters, "incident", PAGE + 1, condition, filters.reason, {"topic": filters.topic})
    found = [_incident(*row) for row in rows]
    found.sort(key=lambda i: i.time, reverse=True)
    return found[:PAGE], len(found) > PAGE


def file_url(key: str) -> str:
    return "/incident-file?key=" + quote(key, safe="")


def _utc(seconds: float) -> str:
    return dt.datetime.fromtimestamp(seconds, dt.UTC).strftime("%H:%M:%S") if seconds else NONE


def page(found: list[Incident], more: bool, filters: Filters) -> str:
    rows = []
    for item in found:
        topics = "".join(
            f'<li class="{"no" if absent else ""}">{escape(topic)}: '
            + ("absent" if absent else f"{messages:,} messages, {_size(size)}{_lost(bound, transport)}")
            + "</li>"
            for topic, messages, size, absent, bound, transport in item.topics
        )
        file_name = escape(item.key.rsplit("/", 1)[-1])
        download = (
            f'<a class="download" href="{escape(file_url(item.key))}" download>{file_name}</a>'
            if item.key
            else '<span class="no">not uploaded</span>'
        )
        cut = ' <span class="bad" title="max_memory_mb let messages of the window go">cut</span>' if item.cut else ""
        rows.append(
            f"<tr class=incident><td class=when>{when(item.time)}</td><td>{escape(item.robot)}</td>"
            f"<td>{escape(item.run)}</td><td>{escape(item.name)}</td>"
            f"<td>{_utc(item.start)} to {_utc(item.end)} ({item.end - item.start:.1f} s){cut}</td>"
            f"<td class=reasons>{escape(', '.join(item.reasons))}</td><td><ul class=topics>{topics}</ul></td>"
            f"<td class=num>{_size(item.size)}</td><td>{download}</td></tr>"
        )
    cards = stat("incidents", f"{len(found)}{'+' if more else ''}", "incidents on this page") + stat(
        "incident-bytes", _size(sum(i.size for i in found)), "in their files"
    )
    search = _page_form(
        "/incidents",
        filters,
        f'<label>Reason (contains)<input type="search" name="reason" id="reason-search" '
        f'value="{escape(filters.reason)}" placeholder="bumper"></label>'
        f'<label>Topic in the file (contains)<input type="search" name="topic" id="topic-search" '
        f'value="{escape(filters.topic)}" placeholder="/scan"></label>',
        drop="reason",
    )
    older = (
        f'<p><a class="button" id="older" href="/incidents{escape(filters.query(before=found[-1].time))}">older</a></p>'
        if more and found
        else ""
    )
    table = (
        '<table id="incidents-table"><tr><th>time</th><th>robot</th><th>run</th><th>recorder</th>'
        "<th>window (UTC)</th><th>reasons</th><th>topics</th><th class=num>size</th><th>file</th></tr>"
        f"{''.join(rows)}</table>{older}"
        if rows
        else f'<p class="no">no incident{_searched(filters)} for these filters</p>'
    )
    return f'{search}<div class="cards">{cards}</div><div class="panel">{table}</div>'


def _searched(filters: Filters) -> str:
    said = []
    if filters.reason:
        said.append(f"a reason holding {escape(filters.reason)}")
    if filters.topic:
        said.append(f"messages of a topic holding {escape(filters.topic)}")
    return (" with " + " and ".join(said)) if said else "s"


def open_file(images: ImageStore, key: str) -> tuple[int, Generator[bytes, None, None]]:
    """The MCAP object's length and its bytes in chunks; DashboardError if it is missing or not an MCAP file."""
    settings = images.settings
    if not settings.configured:
        raise DashboardError("no S3 bucket set")
    if not key or not key.lower().endswith(".mcap") or ".." in key.split("/"):
        raise DashboardError("not an incident file's key")
    try:
        response = images._s3().get_object(Bucket=settings.bucket, Key=key)
        length = int(response.get("ContentLength") or 0)
        body = response["Body"]
        head = body.read(len(MCAP_MAGIC))
    except Exception as exc:  # botocore raises many unrelated types; all mean the same here
        raise DashboardError(f"S3 bucket {settings.bucket!r}, {key}: {_reason(exc)}") from None
    if head != MCAP_MAGIC:
        body.close()
        raise DashboardError(f"{key} is not an MCAP file")

    def chunks() -> Generator[bytes, None, None]:
        try:
            yield head
            while chunk := body.read(CHUNK):
                yield chunk
        finally:
            body.close()

    return length, chunks()
