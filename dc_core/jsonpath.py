"""`/`-separated key paths into JSON objects and arrays, flattening and nesting helpers."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

_ABSENT = object()


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


def flatten(document: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """JSON-pointer style flattening (``{"/a/b": 1, "/l/0": 2}``), as the original's ``flatten``."""
    out: dict[str, Any] = {}

    def walk(node: Any, path: str) -> None:
        if isinstance(node, Mapping) and node:
            for key, value in node.items():
                walk(value, f"{path}/{key}")
        elif isinstance(node, list) and node:
            for i, value in enumerate(node):
                walk(value, f"{path}/{i}")
        else:
            out[path] = node

    for key, value in document.items():
        walk(value, f"{prefix}/{key}")
    return out
