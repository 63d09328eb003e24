"""Building a group's output record from the records of one synchronised set.

Layout of the output (keys in this order)::

    {<key of input 1>: {...record without "tags"...}, <key of input 2>: {...}, ...,
     "missing_inputs": [<topics>]   # only in an incomplete set published with emit_partial
     "tags": [...],                 # when the group has tags
     "name": "<group id>",          # when include_group_name
     "robot_name": "...", "run_id": "..."}  # from the first member that has each (members keep theirs)

``robot_name`` and ``run_id`` sit at the top level of a group's record as they do in a measurement's,
so a query (and the PgSQL destination's typed columns) finds them in one place for every record.

The key of an input's record is the ``group_key`` of its message, or the last segment of its topic
when that is empty. Two records wanting the same key, or a key the group itself writes, never
overwrite each other: in the order of the group's ``inputs``, the first keeps the key and the next
get ``<key>_2``, ``<key>_3``... (first free suffix).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from typing import Any

from dc_core.jsonpath import flatten
from dc_core.records import MalformedRecord, measurement_of, parse_record
from dc_group.config import GroupConfig

MISSING_INPUTS_KEY = "missing_inputs"
TAGS_KEY = "tags"
NAME_KEY = "name"
# Identity keys lifted from the members to the group's top level.
LIFTED_KEYS = ("robot_name", "run_id")


@dataclass(frozen=True)
class InputRecord:
    """One input message, parsed: where it came from, under which key it goes, its record."""

    topic: str
    key: str
    record: dict[str, Any]


@dataclass
class MergedRecord:
    record: dict[str, Any]
    # (wanted key, key given) for every record moved aside by a collision.
    renamed: list[tuple[str, str]] = field(default_factory=list)


def record_key(group_key: str, topic: str) -> str:
    """Key of an input's record in the group: its group_key, else the topic's last segment."""
    if group_key:
        return group_key
    return measurement_of(topic) or topic


def parse_input(topic: str, group_key: str, data: str) -> InputRecord:
    """Parse a StringStamped's data; raises :class:`MalformedRecord` unless it is a JSON object."""
    try:
        record = parse_record(data)
    except MalformedRecord as exc:
        preview = data if len(data) <= 80 else data[:77] + "..."
        raise MalformedRecord(f"data of a message on {topic}: {exc}: {preview!r}") from None
    return InputRecord(topic=topic, key=record_key(group_key, topic), record=record)


def reserved_keys(group: GroupConfig) -> set[str]:
    """Top-level keys the group writes itself (static per configuration, so keys stay stable)."""
    keys = {MISSING_INPUTS_KEY, *LIFTED_KEYS}
    if group.tags:
        keys.add(TAGS_KEY)
    if group.include_group_name:
        keys.add(NAME_KEY)
    return keys


def merge(group: GroupConfig, members: Sequence[InputRecord | None]) -> MergedRecord:
    """The output record of one set; ``members`` follows ``group.inputs``, None where missing."""
    taken = reserved_keys(group)
    merged: dict[str, Any] = {}
    renamed: list[tuple[str, str]] = []
    for member in members:
        if member is None:
            continue
        key = member.key
        if key in taken:
            key = _free_key(member.key, taken)
            renamed.append((member.key, key))
        taken.add(key)
        merged[key] = {k: v for k, v in member.record.items() if k != TAGS_KEY}
    document: dict[str, Any] = exclude(merged, group.exclude_keys) if group.exclude_keys else merged
    if not group.nested_data:
        document = flatten_dotted(document)
    missing = [topic for topic, member in zip(group.inputs, members, strict=True) if member is None]
    if missing:
        document[MISSING_INPUTS_KEY] = missing
    if group.tags:
        document[TAGS_KEY] = list(group.tags)
    if group.include_group_name:
        document[NAME_KEY] = group.name
    for lifted in LIFTED_KEYS:
        # Taken before exclude_keys: a group that drops the members' copies (``*.run_id``) keeps one.
        value = next((m.record[lifted] for m in members if m is not None and lifted in m.record), None)
        if value is not None:
            document[lifted] = value
    return MergedRecord(document, renamed)


def _free_key(key: str, taken: set[str]) -> str:
    n = 2
    while f"{key}_{n}" in taken:
        n += 1
    return f"{key}_{n}"


def exclude(document: dict[str, Any], patterns: Sequence[str]) -> dict[str, Any]:
    """Copy of ``document`` without the paths matching ``patterns`` (and what lies below them).

    A pattern is a '.'-separated key path; each part is matched against one key (or array index)
    with shell wildcards, so ``*.run_id`` removes ``run_id`` from every input's record and
    ``memory.used`` removes exactly that key — not ``memory.used_percent``.
    """
    split = [tuple(p.split(".")) for p in patterns]
    pruned = _prune(document, split)
    assert isinstance(pruned, dict)
    return pruned


def _prune(node: Any, patterns: list[tuple[str, ...]]) -> Any:
    if isinstance(node, dict):
        items = list(node.items())
    elif isinstance(node, list):
        items = [(str(i), v) for i, v in enumerate(node)]
    else:
        return node
    kept: list[tuple[str, Any]] = []
    for key, value in items:
        below = [p[1:] for p in patterns if fnmatchcase(str(key), p[0])]
        if any(not rest for rest in below):
            continue
        kept.append((key, _prune(value, below) if below else value))
    if isinstance(node, dict):
        return dict(kept)
    return [value for _, value in kept]


def flatten_dotted(document: dict[str, Any]) -> dict[str, Any]:
    """``{"a": {"b": 1, "l": [2]}}`` -> ``{"a.b": 1, "a.l.0": 2}``; empty objects and arrays stay."""
    # flatten's paths all start with the separator: one "." too many here.
    return {path[1:]: value for path, value in flatten(document, separator=".").items()}
