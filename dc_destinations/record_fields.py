"""Where a record names a file: a dotted field read in the record's plain, nested or flattened shape.

Apart from the object stores (which need boto3) so that what only reads records — the saved-files
account of the disk budget — imports nothing of theirs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any


def _walk(node: Any, parts: Sequence[str]) -> Any:
    for part in parts:
        if isinstance(node, Mapping) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            return None
    return node


def field_value(data: Mapping[str, Any], dotted: str) -> Any:
    """The value at ``dotted`` (``local_paths.pgm``) in a record; None when it has none.

    Also found in the shapes a measurement's ``nested`` and ``flatten`` give the record:
    ``{"map": {"local_paths": …}}``, ``{"/local_paths/pgm": …}`` and ``{"/map/local_paths/pgm": …}``
    (the original's nested and flattened records), the measurement's name taken from ``name``.
    """
    parts = [part for part in dotted.split(".") if part]
    found = _walk(data, parts)
    if found is not None:
        return found
    pointer = "/" + "/".join(parts)
    if pointer in data:
        return data[pointer]
    name = data.get("name")
    if isinstance(name, str) and name:
        if f"/{name}{pointer}" in data:
            return data[f"/{name}{pointer}"]
        return _walk(data.get(name), parts)
    return None
