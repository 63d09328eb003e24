"""Charts as inline SVG: a time series chart and a trajectory over the map. Pure functions of the data.

No JavaScript and no chart library: the browser draws what the server computed, a test reads the
points off the DOM, and a screenshot is the page as a user sees it.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from html import escape

from dc_dashboard.queries import Series

# Okabe-Ito: tells apart for the usual colour blindnesses.
PALETTE = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00", "#F0E442", "#000000")


def nice_ticks(low: float, high: float, count: int = 5) -> list[float]:
    """Round-numbered ticks covering [low, high]."""
    if not math.isfinite(low) or not math.isfinite(high):
        return []
    if high <= low:
        high = low + 1.0
    raw = (high - low) / max(count, 1)
    magnitude = 10 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw)
    first = math.floor(low / step) * step
    ticks, value = [], first
    while value <= high + step * 1e-9:
        if value >= low - step * 1e-9:
            ticks.append(round(value, 10))
        value += step
    return ticks


def _time_label(seconds: float, span: float) -> str:
    moment = dt.datetime.fromtimestamp(seconds, dt.UTC)
    if span < 120:
        return moment.strftime("%H:%M:%S")
    if span < 2 * 86400:
        return moment.strftime("%H:%M")
    return moment.strftime("%m-%d %H:%M")


def _number(value: float) -> str:
    return f"{value:.0f}" if abs(value) >= 100 or value == int(value) else f"{value:.1f}"


def time_chart(
    series: Sequence[Series],
    *,
    chart_id: str,
    unit: str,
    y_range: tuple[float, float] | None = None,
    empty: str = "nothing stored for these filters",
) -> str:
    """A line per series over time; points are (epoch seconds, value); ``empty``: said when there are none."""
    width, height, left, right, top, bottom = 900, 260, 56, 16, 14, 34
    points = [p for s in series for p in s.points]
    if not points:
        return _empty(chart_id, width, 120, empty)
    t0, t1 = min(p[0] for p in points), max(p[0] for p in points)
    if y_range is None:
        v0, v1 = min(p[1] for p in points), max(p[1] for p in points)
        v0, v1 = (min(v0, 0.0), v1 * 1.1 if v1 > 0 else 1.0)
    else:
        v0, v1 = y_range
    t1 = t1 if t1 > t0 else t0 + 1
    v1 = v1 if v1 > v0 else v0 + 1

    def x(t: float) -> float:
        return left + (t - t0) / (t1 - t0) * (width - left - right)

    def y(v: float) -> float:
        return top + (1 - (v - v0) / (v1 - v0)) * (height - top - bottom)

    parts = [
        f'<svg id="{chart_id}" class="chart" viewBox="0 0 {width} {height}" role="img" '
        f'aria-label="{escape(unit)} over time" preserveAspectRatio="xMidYMid meet">'
    ]
    for tick in nice_ticks(v0, v1):
        parts.append(f'<line class="grid" x1="{left}" x2="{width - right}" y1="{y(tick):.1f}" y2="{y(tick):.1f}"/>')
        parts.append(
            f'<text class="tick" x="{left - 6}" y="{y(tick) + 4:.1f}" text-anchor="end">{_number(tick)}</text>'
        )
    for tick in nice_ticks(t0, t1, 6):
        parts.append(
            f'<text class="tick" x="{x(tick):.1f}" y="{height - 12}" text-anchor="middle">'
            f"{_time_label(tick, t1 - t0)}</text>"
        )
    parts.append(f'<text class="unit" x="{left - 48}" y="{top + 4}">{escape(unit)}</text>')
    for i, s in enumerate(series):
        color = PALETTE[i % len(PALETTE)]
        coords = " ".join(f"{x(t):.1f},{y(v):.1f}" for t, v in sorted(s.points))
        parts.append(
            f'<polyline class="series" data-points="{len(s.points)}" fill="none" stroke="{color}" '
            f'stroke-width="2" points="{coords}"><title>{escape(s.label)}</title></polyline>'
        )
    parts.append("</svg>")
    return "".join(parts) + legend(series)


def legend(series: Sequence[Series]) -> str:
    if len(series) < 2:
        return ""
    items = "".join(
        f'<span class="key"><i style="background:{PALETTE[i % len(PALETTE)]}"></i>{escape(s.label)}</span>'
        for i, s in enumerate(series)
    )
    return f'<div class="legend">{items}</div>'


def trajectory_chart(series: Sequence[Series], map_record: dict[str, object] | None, map_url: str) -> str:
    """Positions (x, y in metres) over the map's PNG, which spans origin + size * resolution."""
    width, height, pad = 900, 600, 36
    xs = [p[0] for s in series for p in s.points]
    ys = [p[1] for s in series for p in s.points]
    extent = _map_extent(map_record) if map_url else None
    if extent:
        xs += [extent[0], extent[1]]
        ys += [extent[2], extent[3]]
    if not xs:
        return _empty("trajectory", width, 160, "no positions stored for these filters")
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    margin = max(x1 - x0, y1 - y0, 1.0) * 0.05
    x0, x1, y0, y1 = x0 - margin, x1 + margin, y0 - margin, y1 + margin
    scale = min((width - 2 * pad) / (x1 - x0), (height - 2 * pad) / (y1 - y0))  # metres keep their shape

    def px(v: float) -> float:
        return pad + (v - x0) * scale

    def py(v: float) -> float:
        return height - pad - (v - y0) * scale

    parts = [
        f'<svg id="trajectory" class="chart map" viewBox="0 0 {width} {height}" role="img" '
        'aria-label="trajectory over the map" preserveAspectRatio="xMidYMid meet">'
    ]
    if extent:
        mx0, mx1, my0, my1 = extent
        parts.append(
            f'<image id="map-image" href="{escape(map_url)}" x="{px(mx0):.1f}" y="{py(my1):.1f}" '
            f'width="{(mx1 - mx0) * scale:.1f}" height="{(my1 - my0) * scale:.1f}" preserveAspectRatio="none" '
            'style="image-rendering:pixelated"/>'
        )
    for tick in nice_ticks(x0, x1, 8):
        parts.append(f'<line class="grid" x1="{px(tick):.1f}" x2="{px(tick):.1f}" y1="{pad}" y2="{height - pad}"/>')
        parts.append(
            f'<text class="tick" x="{px(tick):.1f}" y="{height - pad + 16}" text-anchor="middle">{_number(tick)}</text>'
        )
    for tick in nice_ticks(y0, y1, 6):
        parts.append(f'<line class="grid" x1="{pad}" x2="{width - pad}" y1="{py(tick):.1f}" y2="{py(tick):.1f}"/>')
        parts.append(
            f'<text class="tick" x="{pad - 6}" y="{py(tick) + 4:.1f}" text-anchor="end">{_number(tick)}</text>'
        )
    parts.append(f'<text class="unit" x="{width - pad}" y="{height - 6}" text-anchor="end">x, y (m)</text>')
    for i, s in enumerate(series):
        color = PALETTE[i % len(PALETTE)]
        coords = " ".join(f"{px(a):.1f},{py(b):.1f}" for a, b in s.points)
        parts.append(
            f'<polyline class="series" data-points="{len(s.points)}" fill="none" stroke="{color}" '
            f'stroke-width="2.5" stroke-linejoin="round" points="{coords}"><title>{escape(s.label)}</title></polyline>'
        )
        if s.points:
            (sx, sy), (ex, ey) = s.points[0], s.points[-1]
            parts.append(
                f'<circle class="start" cx="{px(sx):.1f}" cy="{py(sy):.1f}" r="5" fill="#fff" stroke="{color}" '
                'stroke-width="2"><title>start</title></circle>'
            )
            parts.append(
                f'<circle class="end" cx="{px(ex):.1f}" cy="{py(ey):.1f}" r="6" fill="{color}">'
                "<title>last position</title></circle>"
            )
    parts.append("</svg>")
    return "".join(parts) + legend(series)


def _map_extent(record: dict[str, object] | None) -> tuple[float, float, float, float] | None:
    if not record:
        return None
    origin = record.get("origin")
    if not isinstance(origin, dict):
        return None
    try:
        resolution = float(record["resolution"])  # type: ignore[arg-type]
        x0, y0 = float(origin["x"]), float(origin["y"])
        w, h = float(record["width"]), float(record["height"])  # type: ignore[arg-type]
    except (KeyError, TypeError, ValueError):
        return None
    return x0, x0 + w * resolution, y0, y0 + h * resolution


def _empty(chart_id: str, width: int, height: int, text: str) -> str:
    return (
        f'<svg id="{chart_id}" class="chart empty" viewBox="0 0 {width} {height}" role="img">'
        f'<text x="{width / 2}" y="{height / 2}" text-anchor="middle" class="muted">{escape(text)}</text></svg>'
    )
