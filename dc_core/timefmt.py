"""Record time formats of destinations (``time_format``)."""

from __future__ import annotations

import datetime as dt

TIME_FORMATS = ("double", "iso8601")


def format_stamp(stamp_ns: int, time_format: str) -> float | str:
    """``double``: seconds as a float; ``iso8601``: UTC with zero-padded microseconds and ``Z``."""
    if time_format == "double":
        # Through the decimal text: stamp_ns / 1e9 is off in the last digit for about a quarter of stamps.
        seconds, nanos = divmod(stamp_ns, 1_000_000_000)
        return float(f"{seconds}.{nanos:09d}")
    if time_format == "iso8601":
        seconds, nanos = divmod(stamp_ns, 1_000_000_000)
        moment = dt.datetime.fromtimestamp(seconds, tz=dt.UTC)
        return moment.strftime("%Y-%m-%dT%H:%M:%S") + f".{nanos // 1000:06d}Z"
    raise ValueError(f"unknown time format {time_format!r}")
