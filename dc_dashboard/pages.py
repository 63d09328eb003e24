"""The pages' HTML: pure functions of what the queries returned. Every value shown is escaped."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Collection, Sequence
from html import escape
from typing import Any
from urllib.parse import quote

from dc_core.metrics_document import per_measurement
from dc_dashboard.charts import time_chart, trajectory_chart
from dc_dashboard.filters import FILE_STATES, REFRESH_S, Filters, format_time
from dc_dashboard.health import ServerHealth
from dc_dashboard.queries import Distance, Exploration, FilesPage, Inspection, SystemStats, Trajectory

# Shown where there is no value (a dash, not a zero that would be a measurement).
NONE = "\u2013"

# What fills a panel whose kind of record the table holds none of (not a filter's doing).
NOT_COLLECTED = {
    "distance_traveled": "dc_measurements/DistanceTraveled",
    "cpu": "dc_measurements/Cpu",
    "memory": "dc_measurements/Memory",
}


def not_collected(kind: str) -> str:
    return f"no {kind} records in this table: collect {NOT_COLLECTED[kind]} into it to fill this panel"


PAGES = (
    ("/", "Overview"),
    ("/system", "System"),
    ("/camera", "Camera"),
    ("/incidents", "Incidents"),
    ("/files", "Files"),
    ("/explore", "Explorer"),
    ("/health", "Health"),
    ("/fleet", "Fleet"),
)

STYLE = """
:root { --ink:#1d2330; --muted:#5d6778; --line:#dde2ea; --bg:#f5f7fa; --card:#fff; --accent:#0072B2;
        --ok:#1a7f37; --warn:#9a6700; --bad:#cf222e; }
* { box-sizing: border-box; }
.health.ok { color:var(--ok); } .health.retrying { color:var(--warn); }
.health.failing { color:var(--bad); font-weight:600; }
body { margin:0; font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color: var(--ink); background: var(--bg); }
header { background:#14213d; color:#fff; padding:0 24px; display:flex; align-items:center; gap:28px; height:54px; }
header .brand { font-weight:700; font-size:17px; letter-spacing:.3px; }
header .brand small { font-weight:400; opacity:.7; margin-left:6px; }
nav a { color:#cfd8e6; text-decoration:none; padding:16px 12px; display:inline-block;
        border-bottom:3px solid transparent; }
nav a:hover { color:#fff; }
nav a.active { color:#fff; border-bottom-color:#56B4E9; }
form.filters { display:flex; flex-wrap:wrap; gap:14px; align-items:end; padding:14px 24px; background:var(--card);
               border-bottom:1px solid var(--line); }
form.filters.page { background:none; border:0; padding:0 0 14px; }
pre { margin:0; white-space:pre-wrap; }
form.filters label { display:flex; flex-direction:column; font-size:12px; color:var(--muted); gap:3px; }
form.filters select, form.filters input { font:inherit; padding:5px 8px; border:1px solid #c4ccd8; border-radius:6px;
               background:#fff; min-width:140px; }
button, .button { font:inherit; background:var(--accent); color:#fff; border:0; border-radius:6px; padding:6px 16px;
               cursor:pointer; text-decoration:none; }
a.reset { color:var(--muted); font-size:13px; padding-bottom:7px; }
.quick { display:flex; gap:10px; padding-bottom:7px; font-size:13px; }
.quick a { color:var(--accent); text-decoration:none; } .quick a.active { font-weight:700; }
main { padding:20px 24px 40px; max-width:1280px; }
h1 { font-size:21px; margin:4px 0 16px; }
h2 { font-size:16px; margin:0 0 10px; }
.cards { display:grid; grid-template-columns:repeat(auto-fill, minmax(180px, 1fr)); gap:12px; margin-bottom:18px; }
.stat { background:var(--card); border:1px solid var(--line); border-radius:10px; padding:12px 14px; }
.stat .value { display:block; font-size:24px; font-weight:650; }
.stat .label { color:var(--muted); font-size:13px; }
.panel { background:var(--card); border:1px solid var(--line); border-radius:10px; padding:16px; margin-bottom:18px; }
svg.chart { width:100%; height:auto; display:block; }
svg.map { max-height:640px; background:#fbfcfe; }
svg .grid { stroke:#e7ebf0; stroke-width:1; }
svg .tick, svg .unit { fill:var(--muted); font-size:12px; }
svg .muted { fill:var(--muted); font-size:15px; }
.legend { display:flex; flex-wrap:wrap; gap:14px; font-size:13px; color:var(--muted); margin-top:6px; }
.legend i { display:inline-block; width:14px; height:4px; border-radius:2px; margin-right:6px; vertical-align:middle; }
.notice { border-radius:8px; padding:10px 14px; margin-bottom:14px; border:1px solid; }
.notice.error { background:#fff0f0; border-color:#f3b9bc; color:#8c1d18; }
.notice.warn { background:#fff8e5; border-color:#f0d58c; color:#6b4b00; }
.notice.info { background:#eef6ff; border-color:#b7d4f5; color:#0b3c6e; }
table { width:100%; border-collapse:collapse; font-size:13.5px; }
th { text-align:left; color:var(--muted); font-weight:600; border-bottom:2px solid var(--line); padding:6px 8px; }
td { border-bottom:1px solid var(--line); padding:6px 8px; vertical-align:top; }
td.num, th.num { text-align:right; font-variant-numeric:tabular-nums; white-space:nowrap; }
td.when { white-space:nowrap; }
td.path { font-family: ui-monospace, "DejaVu Sans Mono", monospace; font-size:12.5px; word-break:break-all; }
.yes { color:var(--ok); font-weight:600; } .no { color:var(--muted); } .bad { color:var(--bad); font-weight:600; }
.gallery { display:grid; grid-template-columns:repeat(auto-fill, minmax(300px, 1fr)); gap:14px; }
figure { margin:0; background:var(--card); border:1px solid var(--line); border-radius:10px; overflow:hidden; }
figure img { width:100%; display:block; background:#eef1f5; min-height:120px; }
figcaption { padding:10px 12px; font-size:13px; color:var(--muted); }
.code { display:inline-block; background:#eef6ff; color:#0b3c6e; border-radius:5px; padding:1px 7px; margin:3px 4px 0 0;
        font-family: ui-monospace, "DejaVu Sans Mono", monospace; font-size:12.5px; }
.code b { font-family:system-ui, sans-serif; font-weight:600; font-size:11px; margin-right:5px; color:#3d6ea5; }
.tabs a { margin-right:8px; padding:4px 12px; border-radius:14px; border:1px solid var(--line); text-decoration:none;
          color:var(--ink); background:#fff; font-size:13px; display:inline-block; margin-bottom:10px; }
.tabs a.active { background:var(--accent); border-color:var(--accent); color:#fff; }
footer { color:var(--muted); font-size:12px; padding:0 24px 24px; }
.two { display:grid; grid-template-columns:1fr 1fr; gap:18px; }
@media (max-width: 900px) { .two { grid-template-columns:1fr; } }
"""


def layout(
    *,
    title: str,
    path: str,
    filters: Filters,
    robots: Sequence[str],
    runs: Sequence[str],
    body: str,
    notices: Sequence[tuple[str, str]] = (),
    source: str = "",
    show_filters: bool = True,
) -> str:
    scope = filters.scope().query()
    nav = "".join(
        f'<a href="{href}{escape(scope)}" class="{"active" if href == path else ""}">{label}</a>'
        for href, label in PAGES
    )
    messages = [("warn", p) for p in filters.problems] + list(notices)
    notes = "".join(f'<div class="notice {kind}">{escape(text)}</div>' for kind, text in messages)
    form = _filter_form(path, filters, robots, runs) if show_filters else ""
    return (
        "<!doctype html><html lang=en><head><meta charset=utf-8>"
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"{f'<meta http-equiv=refresh content={filters.refresh}>' if filters.refresh else ''}"
        f"<title>{escape(title)} · DC dashboard</title><style>{STYLE}</style></head><body>"
        f'<header><span class="brand">DC<small>dashboard</small></span><nav>{nav}</nav></header>'
        f"{form}<main><h1>{escape(title)}</h1>{notes}{body}</main>"
        f"<footer>{escape(source)} · times are UTC, as stored</footer></body></html>"
    )


def _filter_form(path: str, filters: Filters, robots: Sequence[str], runs: Sequence[str]) -> str:
    def options(values: Sequence[str], selected: str, everything: str) -> str:
        shown = list(values) if not selected or selected in values else [selected, *values]
        items = [f'<option value="">{everything}</option>']
        items += [
            f'<option value="{escape(v)}"{" selected" if v == selected else ""}>{escape(v)}</option>' for v in shown
        ]
        return "".join(items)

    kept = {"state": filters.state, "name": filters.name, "code": filters.code}
    hidden = "".join(
        f'<input type="hidden" name="{key}" value="{escape(value)}">' for key, value in kept.items() if value
    )
    refresh = "".join(
        f'<option value="{seconds}"{" selected" if seconds == filters.refresh else ""}>'
        f"{f'every {seconds} s' if seconds else 'off'}</option>"
        for seconds in REFRESH_S
    )
    # Quick ranges keep the page's own keys (name, code, state), drop the dates and any older-page key.
    quick = [
        (f"last-{key}", label, filters.query(last=key, start=None, end=None, before=None))
        for key, label in (("15m", "last 15 min"), ("1h", "last hour"), ("24h", "last 24 h"), ("7d", "last 7 days"))
    ]
    if runs:  # runs are listed newest first: the robot's current (or last) run
        quick.append(("run", "this run", filters.query(run=runs[0], last="", start=None, end=None, before=None)))
    links = "".join(
        f'<a id="quick-{key}" class="{"active" if key == f"last-{filters.last}" else ""}" '
        f'href="{path}{escape(query)}">{label}</a>'
        for key, label, query in quick
    )
    return (
        f'<form class="filters" method="get" action="{path}">'
        f'<label>Robot<select name="robot" id="filter-robot" onchange="this.form.run.value=\'\';this.form.submit()">'
        f"{options(robots, filters.robot, 'all robots')}</select></label>"
        f'<label>Run<select name="run" id="filter-run" onchange="this.form.submit()">'
        f"{options(runs, filters.run, 'all runs')}</select></label>"
        f'<label>From (UTC)<input type="datetime-local" step="1" name="start" id="filter-start" '
        f'value="{format_time(filters.start)}"></label>'
        f'<label>To (UTC)<input type="datetime-local" step="1" name="end" id="filter-end" '
        f'value="{format_time(filters.end)}"></label>'
        f'<label>Refresh<select name="refresh" id="filter-refresh" onchange="this.form.submit()">{refresh}</select>'
        f"</label>{hidden}"
        f'<button type="submit" id="filter-apply">Apply</button><a class="reset" href="{path}">reset</a>'
        f'<span class="quick">{links}</span></form>'
    )


def stat(stat_id: str, value: str, label: str) -> str:
    return (
        f'<div class="stat" id="stat-{stat_id}"><span class="value">{escape(value)}</span>'
        f'<span class="label">{escape(label)}</span></div>'
    )


def image_url(key: str) -> str:
    return "/image?key=" + quote(key, safe="")


def when(value: dt.datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M:%S") if value else NONE


def overview(trajectory: Trajectory, distance: Distance, row_estimate: int, collected: Collection[str]) -> str:
    """``collected``: the kinds of record the table holds at all (dc_dashboard.catalog.KINDS)."""
    map_record = trajectory.map
    map_url = image_url(str(map_record["key"])) if map_record and map_record.get("key") else ""
    runs = len({(r, u) for r, u, _ in distance.per_run}) or len(trajectory.series)
    has_distance = "distance_traveled" in collected
    cards = (
        stat(
            "distance",
            f"{distance.total_m:,.1f} m" if has_distance else NONE,
            "distance traveled" if has_distance else "distance traveled: not collected",
        )
        + stat("positions", f"{trajectory.positions:,}", "positions stored")
        + stat("runs", f"{runs:,}", "runs")
        + stat("rows", f"≈{row_estimate:,}", "rows in the table (all robots)")
    )
    map_note = (
        "no map saved for this robot yet: positions only"
        if not map_record
        else (
            "the map was not uploaded to S3: positions only"
            if not map_url
            else "the newest map saved before the last position"
        )
    )
    per_run = "".join(
        f"<tr><td>{escape(robot)}</td><td>{escape(run)}</td><td class=num>{metres:,.2f}</td></tr>"
        for robot, run, metres in distance.per_run[:50]
    )
    table = (
        "<table id=distance-table><tr><th>robot</th><th>run</th><th class=num>metres in the range</th></tr>"
        f"{per_run}</table>"
        if per_run
        else f'<p class="no">{escape(not_collected("distance_traveled"))}</p>'
        if not has_distance
        else '<p class="no">no distance_traveled records for these filters</p>'
    )
    distance_empty = not_collected("distance_traveled") if not has_distance else "nothing stored for these filters"
    return (
        f'<div class="cards">{cards}</div>'
        f'<div class="panel"><h2>Trajectory</h2><p class="no">{map_note}</p>'
        f"{trajectory_chart(trajectory.series, map_record, map_url)}</div>"
        f'<div class="two"><div class="panel"><h2>Distance traveled over time</h2>'
        f"{time_chart(distance.series, chart_id='distance-chart', unit='m', empty=distance_empty)}</div>"
        f'<div class="panel"><h2>Per run</h2>{table}</div></div>'
    )


def system(stats: SystemStats, collected: Collection[str]) -> str:
    """``collected``: the kinds of record the table holds at all (dc_dashboard.catalog.KINDS)."""

    def pct(value: float | None) -> str:
        return NONE if value is None else f"{value:.1f} %"

    def empty(kind: str) -> str:
        return "nothing stored for these filters" if kind in collected else not_collected(kind)

    cards = (
        stat("cpu-average", pct(stats.cpu_average), "CPU, average")
        + stat("cpu-max", pct(stats.cpu_max), "CPU, highest")
        + stat("memory-average", pct(stats.memory_average), "memory used, average")
        + stat("memory-max", pct(stats.memory_max), "memory used, highest")
        + stat("samples", f"{stats.samples:,}", "samples")
    )
    return (
        f'<div class="cards">{cards}</div>'
        f'<div class="panel"><h2>CPU (all cores, %)</h2>'
        f"{time_chart(stats.cpu, chart_id='cpu-chart', unit='%', y_range=(0, 100), empty=empty('cpu'))}</div>"
        f'<div class="panel"><h2>Memory used (%)</h2>'
        f"{time_chart(stats.memory, chart_id='memory-chart', unit='%', y_range=(0, 100), empty=empty('memory'))}"
        "</div>"
    )


def camera(inspections: Sequence[Inspection], more: bool, filters: Filters) -> str:
    figures = []
    for item in inspections:
        codes = (
            "".join(
                f'<span class="code"><b>{escape(str(c.get("type", "")))}</b>{escape(str(c.get("data", "")))}</span>'
                for c in item.codes
            )
            or '<span class="no">no code read</span>'
        )
        image = (
            # The link opens the image at its full size (zoom), in the browser's own viewer.
            f'<a class="zoom" href="{image_url(item.key)}" target="_blank" rel="noopener">'
            f'<img class="inspected" loading="lazy" src="{image_url(item.key)}" '
            f'alt="inspected image of {escape(item.camera)}"></a>'
            if item.key
            else '<p class="notice warn">not uploaded to S3</p>'
        )
        figures.append(
            f"<figure>{image}<figcaption><strong>{escape(item.camera)}</strong> · {when(item.time)} · "
            f"{escape(item.robot)} run {escape(item.run)}<div class=codes>{codes}</div></figcaption></figure>"
        )
    codes_read = sum(len(i.codes) for i in inspections)
    cards = stat("inspections", f"{len(inspections)}{'+' if more else ''}", "inspections on this page") + stat(
        "codes", f"{codes_read}", "codes read on this page"
    )
    older = (
        f'<p><a class="button" id="older" href="/camera{escape(filters.query(before=inspections[-1].time))}">'
        "older</a></p>"
        if more and inspections
        else ""
    )
    gallery = (
        f'<div class="gallery">{"".join(figures)}</div>'
        if figures
        else '<p class="no">no inspected images for these filters</p>'
        if not filters.code
        else f'<p class="no">no inspected image with a code holding {escape(filters.code)} for these filters</p>'
    )
    search = _page_form(
        "/camera",
        filters,
        f'<label>Code read (contains)<input type="search" name="code" id="code-search" '
        f'value="{escape(filters.code)}" placeholder="PAL-1000"></label>',
        drop="code",
    )
    return f'{search}<div class="cards">{cards}</div>{gallery}{older}'


def _page_form(path: str, filters: Filters, fields: str, *, drop: str) -> str:
    """A page's own search form: its ``fields`` plus the shared filters as hidden inputs (``drop``: the field's key)."""
    shared = {
        "robot": filters.robot,
        "run": filters.run,
        "start": "" if filters.last else format_time(filters.start),
        "end": "" if filters.last else format_time(filters.end),
        "last": filters.last,
        "refresh": str(filters.refresh) if filters.refresh else "",
        "name": filters.name,
        "code": filters.code,
    }
    hidden = "".join(
        f'<input type="hidden" name="{key}" value="{escape(value)}">'
        for key, value in shared.items()
        if value and key != drop
    )
    return (
        f'<form class="filters page" method="get" action="{path}">{fields}{hidden}'
        '<button type="submit">Search</button></form>'
    )


def explore(exploration: Exploration, filters: Filters) -> str:
    """Any record name: a chart per numeric field and the newest records, for the filters."""
    options = "".join(
        f'<option value="{escape(n)}"{" selected" if n == filters.name else ""}>{escape(n)}</option>'
        for n in exploration.names
    )
    chooser = _page_form(
        "/explore",
        filters,
        '<label>Record name<select name="name" id="explore-name" onchange="this.form.submit()">'
        f'<option value="">choose one</option>{options}</select></label>',
        drop="name",
    )
    if not filters.name:
        names = "".join(
            f'<li><a href="/explore{escape(filters.query(name=n, before=None))}">{escape(n)}</a></li>'
            for n in exploration.names
        )
        return chooser + (
            f'<div class="panel"><h2>Record names in this table</h2><ul id="explore-names">{names}</ul></div>'
            if names
            else '<p class="no">no records in this table yet</p>'
        )
    charts = "".join(
        f'<div class="panel"><h2>{escape(label)}</h2>{time_chart(series, chart_id=f"explore-chart-{i}", unit="")}</div>'
        for i, (label, series) in enumerate(exploration.charts)
    )
    if not exploration.charts:
        charts = f'<p class="no">the newest {escape(filters.name)} records hold no numbers to plot</p>'
    rows = "".join(
        f"<tr><td class=when>{when(t)}</td><td>{escape(robot)}</td><td>{escape(run)}</td>"
        f"<td class=path><details><summary>{escape(_summary(data))}</summary><pre>{escape(_shown(data))}</pre>"
        "</details></td></tr>"
        for t, robot, run, data in exploration.records
    )
    older = (
        f'<p><a class="button" id="older" '
        f'href="/explore{escape(filters.query(before=exploration.records[-1][0]))}">older</a></p>'
        if exploration.more and exploration.records
        else ""
    )
    table = (
        '<table id="explore-records"><tr><th>time</th><th>robot</th><th>run</th><th>record</th></tr>'
        f"{rows}</table>{older}"
        if rows
        else f'<p class="no">no {escape(filters.name)} records for these filters</p>'
    )
    return f'{chooser}{charts}<div class="panel"><h2>Newest records</h2>{table}</div>'


# A record shown in the explorer's table: enough to read it, never a page of base64.
_SHOWN_CHARS = 2000


def _summary(data: Any) -> str:
    """One line of a record: what a row shows until it is opened."""
    text = json.dumps(data, ensure_ascii=False, sort_keys=True, separators=(", ", ": "))
    return text if len(text) <= 160 else text[:160] + " …"


def _shown(data: Any) -> str:
    text = json.dumps(data, indent=1, ensure_ascii=False, sort_keys=True)
    return text if len(text) <= _SHOWN_CHARS else text[:_SHOWN_CHARS] + f"\n… ({len(text):,} characters)"


def files(page: FilesPage, filters: Filters) -> str:
    labels = {
        "": "all",
        "uploaded": "uploaded",
        "verified": "verified",
        "deleted": "deleted",
        "pending": "not uploaded",
    }
    tabs = "".join(
        f'<a href="/files{escape(filters.query(state=s))}" class="{"active" if s == filters.state else ""}">'
        f"{labels[s]} ({page.counts[s or 'all']:,})</a>"
        for s in FILE_STATES
    )
    cards = (
        stat("files", f"{page.counts['all']:,}", "files")
        + stat("uploaded", f"{page.counts['uploaded']:,}", "uploaded")
        + stat("verified", f"{page.counts['verified']:,}", "verified in the bucket")
        + stat("deleted", f"{page.counts['deleted']:,}", "deleted from the robot")
        + stat("bytes", _size(page.total_bytes), "stored")
    )

    def flag(value: Any, bad_when_false: bool = False) -> str:
        if value:
            return '<span class="yes">yes</span>' if value is True else f'<span class="yes">{when(value)}</span>'
        return '<span class="bad">no</span>' if bad_when_false else '<span class="no">no</span>'

    rows = "".join(
        f"<tr class=file><td class=when>{when(r['timestamp'])}</td><td>{escape(str(r['robot_name']))}</td>"
        f"<td>{escape(str(r['group_name']))}</td>"
        f"<td class=path>{escape(str(r['remote_path']))}</td><td>{escape(str(r['content_type']))}</td>"
        f"<td class=num>{_size(r['size'] or 0)}</td><td>{flag(r['uploaded'], True)}</td>"
        f"<td>{flag(r['verified_at'])}</td>"
        f"<td>{flag(r['deleted'])}</td></tr>"
        for r in page.rows
    )
    more = (
        f'<p class="no">the newest {len(page.rows)} shown; narrow the filters to see older ones</p>'
        if page.more
        else ""
    )
    table = (
        '<table id="files-table"><tr><th>time</th><th>robot</th><th>from</th><th>stored as</th><th>type</th>'
        f"<th class=num>size</th><th>uploaded</th><th>verified</th><th>deleted</th></tr>{rows}</table>{more}"
        if rows
        else '<p class="no">no files for these filters</p>'
    )
    return f'<div class="cards">{cards}</div><div class="tabs">{tabs}</div><div class="panel">{table}</div>'


def health(
    servers: Sequence[ServerHealth],
    last_stored: dict[str, dt.datetime | None],
    storages: Sequence[dict[str, Any]],
    missing_indexes: Sequence[str],
    problems: Sequence[str],
    now: float,
) -> str:
    """``last_stored``: per tag, the time of its newest row, which is the record's own time (its
    stamp, simulated time under a simulator), not when it was stored; ``now``: Unix time, for ages."""
    pending = sum(s.pending for s in servers if not s.error)
    dead = sum(s.dead_letters for s in servers if not s.error)
    reachable = sum(1 for s in servers if not s.error)
    delivered = max((t for s in servers if not s.error and (t := s.last_delivery) is not None), default=None)
    cards = (
        stat("pending", f"{pending:,}" if reachable else NONE, "records waiting in the buffer")
        + stat("dead-letters", f"{dead:,}" if reachable else NONE, "dead letters")
        + stat("last-delivery", _ago(delivered, now), "since the last delivery, any destination")
        + stat("servers", f"{reachable} of {len(servers)}", "metrics servers answering")
    )
    parts = [f'<div class="cards">{cards}</div>']
    parts += [f'<div class="notice error">{escape(p)}</div>' for p in problems]
    if not servers:
        parts.append(
            '<div class="notice info">no metrics URL given: start the dashboard with --metrics URL or --params FILE '
            "(a destination_server with flb.http_server: true) to see pending records and dead letters</div>"
        )
    for server in servers:
        if server.error:
            parts.append(f'<div class="notice error">{escape(server.label)}: {escape(server.error)}</div>')
            continue
        parts += [
            notice(
                f"{server.label}: destination {name} failing: "
                + " — ".join(str(part) for part in (d["health"].get("reason"), d["health"].get("fix")) if part)
            )
            for name, d in sorted(server.destinations.items())
            if isinstance(d.get("health"), dict) and d["health"].get("state") == "failing"
        ]
        rows = "".join(
            f"<tr><td>{escape(name)}</td><td>{_health_state(d)}</td><td class=num>{_int(d.get('received'))}</td>"
            f"<td class=num>{_int(d.get('sent'))}</td>"
            f"<td class=num>{_int(d.get('buffered'))}</td><td class=num>{_age(d.get('oldest_pending_age_s'))}</td>"
            f"<td class=num>{_int(d.get('retried'))}</td><td class=num>{_int(d.get('failed'))}</td>"
            f"<td class=num>{_dead(d.get('dead_letters'))}</td>{_budget_cells(d)}"
            f"<td class=delivered>{_utc(d.get('last_delivery'))}</td>"
            f"<td>{when(last_stored.get(name))}</td>"
            f"<td>{_error(d)}</td></tr>"
            for name, d in sorted(server.destinations.items())
        )
        parts += [
            notice(
                f"{server.label}: destination {name} {d['held']}; its backlog waits in the buffer: "
                f"{_int(d.get('buffered'))} records, the oldest {_age(d.get('oldest_pending_age_s'))} old",
                "info",
            )
            for name, d in sorted(server.destinations.items())
            if d.get("held")
        ]
        parts.append(_saved_files_panel(server))
        parts.append(
            f'<div class="panel"><h2>{escape(server.label)}</h2><table class="destinations">'
            "<tr><th>destination</th><th>health</th><th class=num>received</th><th class=num>sent</th>"
            "<th class=num>pending</th>"
            "<th class=num>oldest pending</th><th class=num>retried</th><th class=num>failed</th>"
            "<th class=num>dead letters</th><th class=num>dropped</th><th class=num>evicted</th><th>held</th>"
            "<th>last delivery</th><th>newest row's record time</th>"
            "<th>last error</th></tr>"
            f"{rows}</table></div>"
        )
    stored = "".join(f"<tr><td>{escape(tag)}</td><td>{when(t)}</td></tr>" for tag, t in sorted(last_stored.items()))
    files_rows = "".join(
        f"<tr><td>{escape(str(s['storage_type']))}</td><td>{when(s['last_verified'])}</td><td>{when(s['last_update'])}</td>"
        f"<td class=num>{_int(s['pending'])}</td><td class=num>{_int(s['deleted'])}</td></tr>"
        for s in storages
    )
    parts.append(
        '<div class="two"><div class="panel"><h2>Newest rows in PostgreSQL, per destination</h2>'
        "<table id=last-stored><tr><th>destination (tag)</th><th>newest row's record time</th></tr>"
        f"{stored or '<tr><td colspan=2 class=no>no rows</td></tr>'}</table></div>"
        '<div class="panel"><h2>Last delivery of files, per storage</h2>'
        "<table id=last-files><tr><th>storage</th><th>last verified</th><th>last update</th>"
        "<th class=num>not uploaded</th><th class=num>deleted</th></tr>"
        f"{files_rows or '<tr><td colspan=5 class=no>no files</td></tr>'}</table></div></div>"
    )
    if missing_indexes:
        parts.append(
            '<div class="notice warn">indexes the dashboard needs on large tables are missing: '
            f"{escape(', '.join(missing_indexes))}. Run dc dashboard --create-indexes (docs/dashboard.md)</div>"
        )
    return "".join(parts)


def _budget_cells(destination: dict[str, Any]) -> str:
    """Dropped by the size limit, evicted by the disk budget (records, and the saved files it carries),
    each with its records per measurement, and why it is held."""
    files = destination.get("files_evicted")
    evicted = _int(destination.get("evicted")) + (f" + {_int(files)} files" if files else "")
    return (
        f"<td class=num>{_int(destination.get('dropped'))}{_per_measurement(destination, 'dropped')}</td>"
        f"<td class=num>{evicted}{_per_measurement(destination, 'evicted')}</td>"
        f"<td class=held>{escape(str(destination.get('held') or ''))}</td>"
    )


def _per_measurement(destination: dict[str, Any], counter: str) -> str:
    """`` (camera 55, health 3)``: whose records, as the measurements have retention priorities of their own."""
    of = per_measurement(destination, counter)
    return " (" + ", ".join(f"{escape(str(m))} {_int(n)}" for m, n in of) + ")" if of else ""


def _saved_files_panel(server: ServerHealth) -> str:
    """The saved files under the disk budget, per measurement: produced, delivered, evicted, kept."""
    measurements = server.saved_files.get("measurements")
    if not isinstance(measurements, dict) or not measurements:
        return ""
    rows = "".join(
        f"<tr><td>{escape(name)}</td><td class=num>{_int(c.get('retention_priority'))}</td>"
        f"<td class=num>{_int(c.get('produced'))}</td><td class=num>{_int(c.get('delivered'))}</td>"
        f"<td class=num>{_int(c.get('evicted'))}</td><td class=num>{_int(c.get('evicted_unsent'))}</td>"
        f"<td class=num>{_int(c.get('kept'))}</td><td class=num>{_int(c.get('kept_bytes'))}</td></tr>"
        for name, c in sorted(measurements.items())
        if isinstance(c, dict)
    )
    return (
        f'<div class="panel"><h2>{escape(server.label)}: saved files under the disk budget</h2>'
        '<table class="saved-files"><tr><th>measurement</th><th class=num>retention priority</th>'
        "<th class=num>produced</th><th class=num>delivered</th><th class=num>evicted</th>"
        "<th class=num>of them unsent</th><th class=num>kept</th><th class=num>kept bytes</th></tr>"
        f"{rows}</table></div>"
    )


def _health_state(destination: dict[str, Any]) -> str:
    """ok, retrying or failing (with for how long, why and the fix in its title); "-" from an older DC."""
    health = destination.get("health")
    if not isinstance(health, dict) or not isinstance(health.get("state"), str):
        return NONE
    state = health["state"]
    if state == "ok":
        return '<span class="health ok">ok</span>'
    lasted = health.get("for_s")
    shown = state + (f" {_age(lasted)}" if isinstance(lasted, int | float) else "")
    why = " — ".join(str(part) for part in (health.get("reason"), health.get("fix")) if part)
    return f'<span class="health {escape(state)}" title="{escape(why)}">{escape(shown)}</span>'


def error_body(message: str) -> str:
    return notice(message, element_id="error")


def notice(message: str, kind: str = "error", element_id: str = "") -> str:
    attribute = f' id="{element_id}"' if element_id else ""
    return f'<div class="notice {kind}"{attribute}>{escape(message)}</div>'


def _int(value: Any) -> str:
    return f"{int(value):,}" if isinstance(value, int | float) else NONE


def _dead(value: Any) -> str:
    text = _int(value)
    return f'<span class="bad">{text}</span>' if isinstance(value, int) and value > 0 else text


def _age(value: Any) -> str:
    return f"{float(value):.1f} s" if isinstance(value, int | float) and value else NONE


def _utc(value: Any) -> str:
    """A Unix time of the metrics as the page's other times: UTC, to the second."""
    if not isinstance(value, int | float):
        return NONE
    return when(dt.datetime.fromtimestamp(value, dt.UTC).replace(tzinfo=None))


def _ago(value: float | None, now: float) -> str:
    return f"{max(now - value, 0.0):,.0f} s ago" if value is not None else NONE


def _error(values: dict[str, Any]) -> str:
    error = escape(str(values.get("last_error") or ""))[:300]
    at = values.get("last_error_time")
    return f"{_utc(at)}: {error}" if error and isinstance(at, int | float) else error


def _size(value: int) -> str:
    size = float(value)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:,.0f} {unit}" if unit == "B" else f"{size:,.1f} {unit}"
        size /= 1024
    return f"{size:,.1f} TiB"
