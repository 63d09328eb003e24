"""ROS 2 topic names as users write them.

ROS 2 topic names allow only alphanumerics, ``_``, ``/``, ``~``, ``{`` and ``}``. The original's
examples use ``/hello-world``, which ROS 2 refuses; DC maps ``-`` to ``_`` (``/hello_world``), says
so once, and rejects any other invalid name with the reason.
"""

from __future__ import annotations

import re

_VALID = re.compile(r"^[A-Za-z0-9_/~{}]+$")


def ros_topic(name: str) -> str:
    """The name DC uses on the wire for a configured topic name."""
    return name.replace("-", "_")


def topic_problem(name: str) -> str | None:
    """Why ``name`` cannot be a topic even after mapping, or None."""
    mapped = ros_topic(name)
    if not mapped:
        return "a topic name cannot be empty"
    if not _VALID.match(mapped):
        return "a topic name may hold only letters, digits, '_', '/', '~', '{' and '}'"
    if "//" in mapped:
        return "a topic name cannot contain '//'"
    if mapped.endswith("/") and mapped != "/":
        return "a topic name cannot end with '/'"
    if mapped.lstrip("/")[:1].isdigit():
        return "a topic name cannot start with a digit"
    return None
