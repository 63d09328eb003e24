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


# DC's own topics, relative: each resolves in the namespace of the node that publishes or reads it,
# so DCs started with different --namespace values in one ROS domain never share one. Without a
# namespace they are /dc/measurement/<id>, /dc/group/<group>, /dc/condition/<name>, as they always were.
MEASUREMENT_TOPIC_PREFIX = "dc/measurement/"
GROUP_TOPIC_PREFIX = "dc/group/"
CONDITION_TOPIC_PREFIX = "dc/condition/"
ROOT_DC_PREFIX = "/dc/"


def ros_namespace(namespace: str) -> str:
    """``robot1``, ``/robot1/`` or ``""`` as ROS writes a node's namespace: ``/robot1`` or ``/``."""
    return "/" + namespace.strip("/")


def resolve_topic(name: str, namespace: str = "/", node: str = "") -> str:
    """The fully qualified name rcl expands ``name`` to for node ``node`` in ``namespace``, before remapping.

    Absolute names stay; ``~`` is the node's own name space; ``{node}`` and ``{ns}``/``{namespace}``
    are substituted (rcl_expand_topic_name's rules, checked against rclpy in the tests). Config
    parsing needs no ROS context, so this does not call into rcl.
    """
    ns = ros_namespace(namespace)
    base = ns.rstrip("/")
    expanded = name.replace("{node}", node).replace("{namespace}", ns).replace("{ns}", ns)
    if expanded.startswith("/"):
        return expanded
    if expanded.startswith("~"):
        return f"{base}/{node}{expanded[1:]}"
    return f"{base}/{expanded}"


def outside_namespace(topics: list[str], namespace: str) -> list[str]:
    """The names among ``topics`` (fully qualified) that are DC's own names left at the root while
    DC runs in ``namespace``: written absolute (``/dc/…``), every DC of the domain shares them."""
    if ros_namespace(namespace) == "/":
        return []
    return [t for t in dict.fromkeys(topics) if t.startswith(ROOT_DC_PREFIX)]
