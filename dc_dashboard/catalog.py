"""Which stored records hold what: found from the records' shapes, whatever the measurements were named.

A position can be a row of its own (``name: position``) or a member of a group (``robot`` holds
``position``, ``cmd_vel``, ``speed``); the dashboard finds both by looking at the newest rows of each
record name, so a renamed measurement or a new group needs no setting.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

KINDS = ("position", "cpu", "memory", "distance_traveled", "map", "camera", "incident")
# Nested objects of a measurement that are not group members (a map's origin has x, y and yaw too).
_NOT_MEMBERS = {"origin", "local_paths", "remote_paths", "base64", "inspected", "linear", "angular", "sorted"}


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def kind_of(record: Mapping[str, Any]) -> str | None:
    if "camera_name" in record:
        return "camera"
    if isinstance(record.get("triggers"), list) and "cut_by_memory_bound" in record:
        return "incident"  # dc_measurements/Recorder
    if all(k in record for k in ("resolution", "origin", "width", "height")):
        return "map"
    if _number(record.get("distance_traveled")):
        return "distance_traveled"
    if _number(record.get("average")) and "processes" in record:
        return "cpu"
    if all(_number(record.get(k)) for k in ("x", "y", "yaw")):
        return "position"
    if _number(record.get("used")) and "capacity" not in record and "total" not in record:
        return "memory"
    return None


def find_kinds(
    record: Mapping[str, Any], path: tuple[str, ...] = (), depth: int = 2
) -> Iterator[tuple[str, tuple[str, ...]]]:
    """(kind, JSON path of that measurement in the record) for the record and its group members."""
    kind = kind_of(record)
    if kind is not None:
        yield kind, path
        return
    if depth == 0:
        return
    for key, value in record.items():
        if isinstance(value, dict) and key not in _NOT_MEMBERS:
            yield from find_kinds(value, (*path, key), depth - 1)


Sources = dict[str, list[tuple[str, tuple[str, ...]]]]


def sources_of(latest: Mapping[str, list[Mapping[str, Any]]]) -> Sources:
    """kind → [(record name, path)], from a few newest records of each name."""
    found: Sources = {kind: [] for kind in KINDS}
    for name, records in sorted(latest.items()):
        for record in records:
            for kind, path in find_kinds(record):
                if (name, path) not in found[kind]:
                    found[kind].append((name, path))
    return found


# Keys DC writes on every record that are not measurements: plotting them tells nothing.
_BOOKKEEPING = {"date", "run_id", "id", "record_id", "schema_version"}
MAX_FIELDS = 16


def numeric_fields(records: list[Mapping[str, Any]], depth: int = 3) -> list[tuple[str, ...]]:
    """JSON paths of the numbers in a record name's newest records (the explorer's plots), at most MAX_FIELDS."""
    found: list[tuple[str, ...]] = []

    def walk(value: Mapping[str, Any], path: tuple[str, ...], left: int) -> None:
        for key, item in value.items():
            if len(found) >= MAX_FIELDS:
                return
            if _number(item) and key not in _BOOKKEEPING and (*path, key) not in found:
                found.append((*path, key))
            elif isinstance(item, dict) and left > 1:
                walk(item, (*path, key), left - 1)

    for record in records:
        walk(record, (), depth)
    return found
