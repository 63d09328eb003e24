"""The Fleet page: every robot of the table, when it was last seen, its records today, and the
destinations failing on it, from the health records it sends (docs/fleet.md).

A robot's health reaches the table as records: its destination_server publishes the state of its
destinations on ``dc/destination_health`` (JSON ``{"<destination>": {"state", "since", "reason",
"fix"}}``, on every change), and a StringStamped measurement named ``destination_health`` forwards
it like any record. The newest such record of a robot says which of its destinations fail.

The queries are bounded as the other pages' (dc_dashboard.queries): the robots are read by skipping
through the (robot, name, time) index, and a robot's last row is the newest of its names' last rows,
a seek per name in that same index: (robots x names) seeks, whatever the table's size. Its records
today are counted the same way (the rows of its names since midnight) while the planner expects at
most ``EXACT_UP_TO`` rows today; a count reads every row it counts, so above that (a fleet's day:
25 million rows would take over a minute here) they are estimates, said as such on the page: the
robot's rows per second over its history (the planner's count of its rows from ANALYZE's
statistics, over the time from its first row to its last) times its time active today (its first
row today to its last) — seeks again; exact for a robot without a row today, off by what its rate
today differs from its average, or by its pauses today. Every robot's count of rows comes from one
read of the statistics (``robot_rows``), not a plan per robot.
"""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from html import escape
from typing import Any
from urllib.parse import quote

from dc_dashboard import indexes
from dc_dashboard.filters import Filters
from dc_dashboard.pages import NONE, notice, stat, when
from dc_dashboard.queries import Store

HEALTH_RECORD = "destination_health"  # the name of the measurement forwarding dc/destination_health
# Rows today above which the records today are the planner's estimates: counting reads every row of
# the day (~3 us each here), 1.8 M rows took 5.5 s on this 2-core machine (benchmarks/dashboard_fleet.py).
EXACT_UP_TO = 200_000
FAILING, RETRYING = "failing", "retrying"


@dataclass
class RobotRow:
    robot: str
    last_seen: dt.datetime | None
    records_today: int
    health_at: dt.datetime | None = None  # the time of its newest health record, None without any
    failing: list[tuple[str, str]] = field(default_factory=list)  # (destination, reason — fix)
    retrying: list[str] = field(default_factory=list)


def overview(
    store: Store, connection: Any, filters: Filters, now: dt.datetime, exact_up_to: int = EXACT_UP_TO
) -> tuple[list[RobotRow], bool]:
    """A row per robot (the robot filter's alone when set), most recently seen first; ``now`` naive UTC.
    And whether the records today are the planner's estimates (more than ``exact_up_to`` rows today)."""
    from psycopg import sql

    robots = [filters.robot] if filters.robot else store.robots(connection)
    names = sorted(store.catalog(connection).fields)
    if not robots or not names:
        return [], False
    today = now.replace(hour=0, minute=0, second=0, microsecond=0)
    last_seen = _per_robot(store, "max(last.time)", ("last", "max(time) AS time", "time >= %(since)s"))
    # Since yesterday first: on a table partitioned by time, a seek without a bound on time is one
    # per partition; the robots not seen since then are looked for in the whole table.
    params: dict[str, Any] = {"robots": robots, "names": names, "today": today, "since": today - dt.timedelta(days=1)}
    rows: dict[str, RobotRow] = {}
    for since in (params["since"], dt.datetime.min):
        params["since"] = since
        for robot, last in connection.execute(last_seen, params).fetchall():
            if last is not None:
                rows[robot] = RobotRow(robot, _naive(last), 0)
        params["robots"] = [r for r in robots if r not in rows]
        if not params["robots"]:
            break
    estimated = _estimate(connection, store, sql.SQL("time >= {}").format(sql.Literal(today))) > exact_up_to
    if estimated:
        # The robot's rows per second over its whole history (the planner's count of its rows, its
        # first and last row: seeks) times its time active today (its first row today to its last).
        spans = _per_robot(
            store,
            "min(first.time), min(first_today.time)",
            ("first", "min(time) AS time", ""),
            ("first_today", "min(time) AS time", "time >= %(today)s"),
        )
        params["robots"] = list(rows)
        totals = robot_rows(connection, store)
        for robot, first, first_today in connection.execute(spans, params).fetchall():
            row, first, first_today = rows[robot], _naive(first), _naive(first_today)
            if first is None or first_today is None or row.last_seen is None:
                continue  # no row today: 0, known
            if totals is not None:
                total = round(totals(robot))
            else:
                total = _estimate(connection, store, sql.SQL("{} = {}").format(indexes.ROBOT, sql.Literal(robot)))
            lived = (row.last_seen - first).total_seconds()
            active = (row.last_seen - first_today).total_seconds()
            row.records_today = round(total * active / lived) if lived > 0 else total
    else:
        counts = _per_robot(store, "sum(today.rows)::bigint", ("today", "count(*) AS rows", "time >= %(today)s"))
        params["robots"] = list(rows)
        for robot, count in connection.execute(counts, params).fetchall():
            rows[robot].records_today = int(count or 0)
    health = sql.SQL(
        "SELECT r.robot, h.time, h.data FROM unnest(%(robots)s::text[]) AS r(robot)"
        " CROSS JOIN LATERAL (SELECT time, data FROM {t} WHERE {robot} = r.robot AND (data->>'name') = %(health)s"
        "   ORDER BY time DESC LIMIT 1) AS h"
    ).format(t=store.table, robot=indexes.ROBOT)
    for robot, at, data in connection.execute(health, {"robots": list(rows), "health": HEALTH_RECORD}).fetchall():
        row = rows[robot]
        row.health_at = _naive(at)
        for destination, state in sorted(data.items() if isinstance(data, dict) else ()):
            if not isinstance(state, dict):
                continue  # the record's own keys (name, robot_name, run_id, date…)
            if state.get("state") == FAILING:
                why = " — ".join(str(state[k]) for k in ("reason", "fix") if state.get(k))
                row.failing.append((destination, why))
            elif state.get("state") == RETRYING:
                row.retrying.append(destination)
    ordered = sorted(rows.values(), key=lambda r: (r.last_seen or dt.datetime.min, r.robot), reverse=True)
    return ordered, estimated


def _per_robot(store: Store, columns: str, *seeks: tuple[str, str, str]) -> Any:
    """``SELECT r.robot, <columns>`` of each robot of %(robots)s over its names %(names)s, each
    ``(alias, select, where)`` of ``seeks`` a subquery over one (robot, name) pair's rows (and
    ``where``, if any): a seek in the (robot, name, time) index per pair, whatever the table's size."""
    from psycopg import sql

    laterals = "".join(
        f" CROSS JOIN LATERAL (SELECT {select} FROM {{t}}"
        f"   WHERE {{robot}} = r.robot AND (data->>'name') = n.name{f' AND {where}' if where else ''}) AS {alias}"
        for alias, select, where in seeks
    )
    return sql.SQL(
        f"SELECT r.robot, {columns}"
        " FROM unnest(%(robots)s::text[]) AS r(robot) CROSS JOIN unnest(%(names)s::text[]) AS n(name)"
        f"{laterals} GROUP BY r.robot"
    ).format(t=store.table, robot=indexes.ROBOT)


def robot_rows(connection: Any, store: Store) -> Callable[[str], float] | None:
    """The rows of a robot in the table as the planner would estimate ``ROBOT = robot``, for every robot
    from one read of the statistics: ANALYZE's most common values of the robot expression (kept with
    the dashboard's (robot, name, time) index, of each partition on a partitioned table) times the
    rows of the table or partition. An ``EXPLAIN`` per robot plans over every partition: 100 robots on
    30 day partitions took 1.6 s. None when a table with rows has no such statistics readable here
    (the index missing, not analysed yet, or a role that does not own the table: pg_stats shows an
    index's statistics to its owner only): the caller plans per robot then."""
    from psycopg import sql

    table, name = indexes.table_and_name(store.settings, indexes.ROBOT_INDEX)
    index = sql.Identifier(*table.split(".")[:-1], name).as_string(connection)
    found = connection.execute(
        "SELECT greatest(c.reltuples, 0), s.most_common_vals::text::text[], s.most_common_freqs, s.null_frac,"
        " s.n_distinct"
        " FROM pg_partition_tree(to_regclass(%s)) AS p JOIN pg_index i ON i.indexrelid = p.relid"
        " JOIN pg_class c ON c.oid = i.indrelid JOIN pg_class ic ON ic.oid = i.indexrelid"
        " JOIN pg_namespace n ON n.oid = ic.relnamespace JOIN pg_attribute a ON a.attrelid = ic.oid AND a.attnum = 1"
        " LEFT JOIN pg_stats s ON s.schemaname = n.nspname AND s.tablename = ic.relname AND s.attname = a.attname"
        " WHERE p.isleaf",
        (index,),
    ).fetchall()
    parts: list[tuple[float, dict[str, float], float]] = []  # rows, robot -> share, share of another robot
    for rows, values, freqs, null_frac, n_distinct in found:
        if not rows:
            continue
        if null_frac is None:
            return None
        common = dict(zip(values or [], freqs or [], strict=True))
        distinct = n_distinct if n_distinct >= 0 else -n_distinct * rows
        # As the planner's equality estimate: what the common values leave, shared by the other values.
        other = max(1.0 - null_frac - sum(common.values()), 0.0) / max(distinct - len(common), 1.0)
        parts.append((float(rows), common, other))
    if not parts:
        return None  # no statistics at all (never analysed): the planner's guesses, per robot
    return lambda robot: sum(rows * common.get(robot, other) for rows, common, other in parts)


def _estimate(connection: Any, store: Store, where: Any) -> int:
    """The rows the planner expects ``where`` to select (ANALYZE's statistics; no row is read)."""
    from psycopg import sql

    query = sql.SQL("EXPLAIN (FORMAT JSON) SELECT 1 FROM {t} WHERE {w}").format(t=store.table, w=where)
    (plan,) = connection.execute(query).fetchone()
    document = json.loads(plan) if isinstance(plan, str) else plan
    return int(document[0]["Plan"]["Plan Rows"])


def _naive(value: dt.datetime | None) -> dt.datetime | None:
    """UTC without a zone, as the pages show times (a timestamptz column gives aware ones)."""
    if value is not None and value.tzinfo is not None:
        return value.astimezone(dt.UTC).replace(tzinfo=None)
    return value


def page(rows: list[RobotRow], now: dt.datetime, estimated: bool = False) -> str:
    failing = [r for r in rows if r.failing]
    hour_ago = now - dt.timedelta(hours=1)
    recent = sum(1 for r in rows if r.last_seen and r.last_seen >= hour_ago)
    approx = "\u2248" if estimated else ""
    today = sum(r.records_today for r in rows)
    stats = (
        '<div class="stats">'
        + stat("robots", f"{len(rows):,}", "robots in the table")
        + stat("seen-last-hour", f"{recent:,}", "seen in the last hour")
        + stat("records-today", f"{approx}{today:,}", f"records today ({now:%Y-%m-%d} UTC)")
        + stat("failing-robots", f"{len(failing):,}", "robots with a failing destination")
        + "</div>"
    )  # fmt: skip
    notices = "".join(
        notice(f"{r.robot}: destination {name} failing: {why or 'no reason given'}", element_id=f"failing-{r.robot}")
        for r in failing
        for name, why in r.failing[:3]
    )
    if estimated:
        notices += notice(
            f"more than {EXACT_UP_TO:,} rows today: the records today are estimates (≈): each robot's average"
            " rate (its rows in PostgreSQL's statistics over its time in the table) times its time active today",
            kind="warn",
            element_id="estimated",
        )
    if not rows:
        return stats + '<p class="no">no robot in this table yet</p>'
    body = "".join(_row(r, now, approx) for r in rows)
    table = (
        '<table id="fleet-table"><tr><th>robot</th><th>last seen (UTC)</th><th class=num>ago</th>'
        "<th class=num>records today</th><th>failing destinations</th><th>health as of</th></tr>"
        f"{body}</table>"
    )
    hint = (
        f'<p class="no">Failing destinations come from each robot\'s newest <code>{HEALTH_RECORD}</code> record '
        "(a StringStamped measurement of <code>dc/destination_health</code>: docs/fleet.md); "
        "a robot without any shows \u2013.</p>"
    )
    return stats + notices + f'<div class="panel"><h2>Robots</h2>{table}{hint}</div>'


def _row(row: RobotRow, now: dt.datetime, approx: str) -> str:
    if row.health_at is None:
        health = NONE
    elif row.failing:
        health = ", ".join(
            f'<span class="health failing" title="{escape(why)}">{escape(name)}</span>' for name, why in row.failing
        )
    else:
        health = '<span class="health ok">none</span>'
    if row.retrying:
        health += " " + ", ".join(f'<span class="health retrying">{escape(n)} retrying</span>' for n in row.retrying)
    ago = _ago(now - row.last_seen) if row.last_seen else NONE
    link = f'<a href="/?robot={quote(row.robot, safe="")}">{escape(row.robot)}</a>'
    return (
        f'<tr data-robot="{escape(row.robot)}"><td>{link}</td>'
        f"<td>{when(row.last_seen)}</td><td class=num>{ago}</td><td class=num>{approx}{row.records_today:,}</td>"
        f"<td>{health}</td><td>{when(row.health_at)}</td></tr>"
    )


def _ago(delta: dt.timedelta) -> str:
    seconds = max(delta.total_seconds(), 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.0f} d"
