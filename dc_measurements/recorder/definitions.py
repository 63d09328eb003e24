"""The text of a ROS 2 message definition (MCAP ``ros2msg`` schema), from the installed interface packages.

The definition of ``pkg/msg/Type`` is its ``.msg`` file followed by those of every type it uses, each
after a line of 80 ``=`` and ``MSG: pkg/Type`` — what rosbag2 writes, and what ``ros2 bag``, Foxglove,
rosbags and the ``mcap`` tools read. The ``.msg`` files come from the share directory of the package
that defines the type on this machine (the type the publisher's wire format follows); a type without
one there is taken from rosbags' copy of the Jazzy types, else it has no definition (None).
"""

from __future__ import annotations

import os
import re
import sys
import threading
from pathlib import Path
from typing import Any

_UNKNOWN = re.compile(r"Type '([^']+)' is unknown")


def _prefixes() -> list[str]:
    # The wheels' interface packages live in the venv's prefix; a sourced ROS adds its own.
    found = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return [*found, sys.prefix] if sys.prefix not in found else found


def _share_msg(typename: str) -> str | None:
    package, _, name = typename.partition("/msg/")
    if not name:
        return None
    for prefix in _prefixes():
        try:
            return (Path(prefix) / "share" / package / "msg" / f"{name}.msg").read_text()
        except OSError:
            continue
    return None


class Definitions:
    """Definitions by type name, built once per type (a recorder asks once per topic)."""

    def __init__(self) -> None:
        self._store: Any = None
        self._jazzy: Any = None
        self._done: dict[str, str | None] = {}
        # Files are written on several worker threads; the type store is not for concurrent use.
        self._lock = threading.Lock()

    def get(self, typename: str) -> str | None:
        with self._lock:
            if typename not in self._done:
                self._done[typename] = self._build(typename)
            return self._done[typename]

    def _build(self, typename: str) -> str | None:
        from rosbags.typesys import get_types_from_msg
        from rosbags.typesys.base import TypesysError

        if self._store is None:  # parsing .msg files costs: on the first file, on the worker
            from rosbags.typesys import Stores, get_typestore

            self._store = get_typestore(Stores.EMPTY)
        missing = typename
        for _ in range(200):  # each round adds one type; no message uses that many
            try:
                if missing not in self._store.fielddefs:
                    self._add(missing, get_types_from_msg)
                text: str = self._store.generate_msgdef(typename, ros_version=2)[0]
                return text
            except TypesysError as exc:
                found = _UNKNOWN.search(str(exc))
                if found is None or found.group(1) == missing:
                    return None
                missing = found.group(1)
        return None

    def _add(self, typename: str, parse: Any) -> None:
        text = _share_msg(typename)
        if text is not None:
            self._store.register(parse(text, typename))
            return
        if self._jazzy is None:
            from rosbags.typesys import Stores, get_typestore

            self._jazzy = get_typestore(Stores.ROS2_JAZZY)
        if typename in self._jazzy.fielddefs:
            self._store.register({typename: self._jazzy.fielddefs[typename]})
