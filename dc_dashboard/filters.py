"""The filters of a view, read from and written to its query string: the URL is the whole state of a page."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field, replace
from urllib.parse import parse_qs, urlencode

# What a datetime-local input sends (seconds when its step allows them); times are UTC, as stored.
_TIME_FORMATS = ("%Y-%m-%dT%H:%M:%S", "%Y-%m-%dT%H:%M", "%Y-%m-%d %H:%M:%S", "%Y-%m-%d")
FILE_STATES = ("", "uploaded", "verified", "deleted", "pending")
# Quick ranges: the start is taken at each request, so an auto-refreshed page follows the clock.
LAST = {
    "15m": dt.timedelta(minutes=15),
    "1h": dt.timedelta(hours=1),
    "24h": dt.timedelta(days=1),
    "7d": dt.timedelta(days=7),
}
REFRESH_S = (0, 10, 30, 60)


@dataclass(frozen=True)
class Filters:
    robot: str = ""
    run: str = ""
    start: dt.datetime | None = None
    end: dt.datetime | None = None
    # Files page: one state or all; camera page: newest first, older pages by keyset.
    state: str = ""
    before: dt.datetime | None = None
    # Quick range (a LAST key: the start follows the clock), page refresh in seconds (0: none).
    last: str = ""
    refresh: int = 0
    # Explorer: the record name; Camera: text a code read must contain.
    name: str = ""
    code: str = ""
    # Incidents: text a trigger's reason must contain, text the name of a topic in the file must contain.
    reason: str = ""
    topic: str = ""
    problems: tuple[str, ...] = field(default=(), compare=False)

    @classmethod
    def parse(cls, query: str, now: dt.datetime | None = None) -> Filters:
        """``now``: naive UTC, for the quick ranges (the clock when None)."""
        values = {k: v[-1].strip() for k, v in parse_qs(query, keep_blank_values=True).items()}
        problems: list[str] = []

        def when(key: str) -> dt.datetime | None:
            text = values.get(key, "")
            if not text:
                return None
            for form in _TIME_FORMATS:
                try:
                    return dt.datetime.strptime(text, form)
                except ValueError:
                    continue
            problems.append(f"{key}: {text!r} is not a date and time (YYYY-MM-DDTHH:MM:SS, UTC); ignored")
            return None

        state = values.get("state", "")
        if state not in FILE_STATES:
            problems.append(f"state: {state!r} is not one of {', '.join(s for s in FILE_STATES if s)}; ignored")
            state = ""
        start, end = when("start"), when("end")
        if start and end and end < start:
            problems.append("the end is before the start: both ignored")
            start = end = None
        last = values.get("last", "")
        if last and last not in LAST:
            problems.append(f"last: {last!r} is not one of {', '.join(LAST)}; ignored")
            last = ""
        if last:  # a quick range replaces the dates
            start, end = (now or dt.datetime.now(dt.UTC).replace(tzinfo=None)) - LAST[last], None
        refresh_text = values.get("refresh", "") or "0"
        refresh = int(refresh_text) if refresh_text.isdigit() and int(refresh_text) in REFRESH_S else 0
        if refresh_text != str(refresh):
            problems.append(f"refresh: {refresh_text!r} is not one of {', '.join(map(str, REFRESH_S))} s; ignored")
        return cls(
            robot=values.get("robot", "")[:200],
            run=values.get("run", "")[:200],
            start=start,
            end=end,
            state=state,
            before=when("before"),
            last=last,
            refresh=refresh,
            name=values.get("name", "")[:200],
            code=values.get("code", "")[:200],
            reason=values.get("reason", "")[:200],
            topic=values.get("topic", "")[:200],
            problems=tuple(problems),
        )

    def query(self, **changes: object) -> str:
        """This view's query string, with ``changes`` applied (None or "" drops a key)."""
        changed = replace(self, **changes) if changes else self  # type: ignore[arg-type]
        quick = changed.last in LAST
        pairs = {
            "robot": changed.robot,
            "run": changed.run,
            "start": "" if quick else format_time(changed.start),
            "end": "" if quick else format_time(changed.end),
            "last": changed.last if quick else "",
            "refresh": str(changed.refresh) if changed.refresh else "",
            "name": changed.name,
            "code": changed.code,
            "reason": changed.reason,
            "topic": changed.topic,
            "state": changed.state,
            "before": format_time(changed.before),
        }
        text = urlencode({k: v for k, v in pairs.items() if v})
        return "?" + text if text else ""

    def scope(self) -> Filters:
        """Only the filters every page shares (what the navigation carries from page to page)."""
        return Filters(
            robot=self.robot, run=self.run, start=self.start, end=self.end, last=self.last, refresh=self.refresh
        )


def format_time(value: dt.datetime | None) -> str:
    return value.strftime("%Y-%m-%dT%H:%M:%S") if value else ""
