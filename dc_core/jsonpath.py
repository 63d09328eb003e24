"""`/`-separated key paths into JSON objects and arrays, flattening and nesting helpers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from dc_core.params import did_you_mean


class PathNotFound(LookupError):
    """The key path does not lead to a value."""


def get_path(document: Any, path: str) -> Any:
    """Value at ``path`` (``inspected/barcode/0/data``); raises :class:`PathNotFound`."""
    node = document
    for part in [p for p in path.strip("/").split("/") if p != ""]:
        if isinstance(node, Mapping):
            if part not in node:
                raise PathNotFound(f"key {part!r} of {path!r} not found")
            node = node[part]
        elif isinstance(node, list):
            try:
                index = int(part)
            except ValueError:
                raise PathNotFound(f"{part!r} of {path!r} is not an array index") from None
            if not -len(node) <= index < len(node):
                raise PathNotFound(f"index {index} of {path!r} out of range")
            node = node[index]
        else:
            raise PathNotFound(f"{path!r} goes through a {type(node).__name__}")
    return node


def has_path(document: Any, path: str) -> bool:
    try:
        get_path(document, path)
    except PathNotFound:
        return False
    return True


def flatten(document: Mapping[str, Any], prefix: str = "", separator: str = "/") -> dict[str, Any]:
    """JSON-pointer style flattening (``{"/a/b": 1, "/l/0": 2}``), as the original's ``flatten``; every
    path starts with ``prefix`` and ``separator``. Empty objects and arrays are leaves."""
    out: dict[str, Any] = {}

    def walk(node: Any, path: str) -> None:
        if isinstance(node, Mapping) and node:
            for key, value in node.items():
                walk(value, f"{path}{separator}{key}")
        elif isinstance(node, list) and node:
            for i, value in enumerate(node):
                walk(value, f"{path}{separator}{i}")
        else:
            out[path] = node

    for key, value in document.items():
        walk(value, f"{prefix}{separator}{key}")
    return out


def impossible_path(schema: Mapping[str, Any], path: str) -> str | None:
    """Why no record valid under ``schema`` can have ``path``, or None when one may.

    Conservative: a path is impossible only where the schema lists an object's ``properties`` and
    forbids others (``additionalProperties: false``, no ``patternProperties``), or where it says a
    value is not an object or array at all. Combinators (``anyOf``, ``$ref``...) end the check.
    """
    return _walk_schema(schema, path)[1]


def schema_types_at(schema: Mapping[str, Any], path: str) -> set[str] | None:
    """The JSON types ``schema`` allows for the value at ``path`` (``integer`` counted as a
    ``number``), or None when the schema does not say (no ``type``, a combinator, an open object)."""
    types = declared_types_at(schema, path)
    if types is None:
        return None
    return types | {"number"} if "integer" in types else types


def declared_types_at(schema: Mapping[str, Any], path: str) -> set[str] | None:
    """The ``type`` ``schema`` declares for the value at ``path``, as written (``integer`` apart from
    ``number``), or None when the schema does not say."""
    node, reason = _walk_schema(schema, path)
    if reason is not None or not isinstance(node, Mapping) or _opaque(node):
        return None
    declared = node.get("type")
    return {declared} if isinstance(declared, str) else set(declared) if isinstance(declared, list) else None


def _opaque(node: Mapping[str, Any]) -> bool:
    return any(k in node for k in ("anyOf", "oneOf", "allOf", "$ref", "not", "if"))


def _walk_schema(schema: Mapping[str, Any], path: str) -> tuple[Any, str | None]:
    """(the schema of the value at ``path`` or None when unknown, why no value can be there or None)."""
    node: Any = schema
    walked: list[str] = []
    for part in [p for p in path.strip("/").split("/") if p != ""]:
        if not isinstance(node, Mapping) or _opaque(node):
            return None, None
        properties = node.get("properties")
        where = "/".join(walked) or "the record"
        if isinstance(properties, Mapping) and part in properties:
            node = properties[part]
        elif node.get("type") == "array" or "items" in node:
            items = node.get("items")
            if not part.lstrip("-").isdigit():
                return None, f"{where} is an array: {part!r} is not an index"
            node = items if isinstance(items, Mapping) else None
        elif node.get("additionalProperties") is False and not node.get("patternProperties"):
            known = sorted(properties) if isinstance(properties, Mapping) else []
            hint = did_you_mean(part, known)
            return None, f"{where} has no key {part!r}{hint}; its keys: {', '.join(known) or 'none'}"
        elif node.get("type") in ("string", "number", "integer", "boolean", "null"):
            return None, f"{where} is a {node['type']}, not an object"
        else:
            extra = node.get("additionalProperties")
            node = extra if isinstance(extra, Mapping) else None
        walked.append(part)
    return node, None
