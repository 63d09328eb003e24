"""ROS 2 topic names as users write them.

ROS 2 topic names allow only alphanumerics, ``_``, ``/``, ``~``, ``{`` and ``}``. The original's
examples use ``/hello-world``, which ROS 2 refuses; DC maps ``-`` to ``_`` (``/hello_world``), says
so once, and rejects any other invalid name with the reason.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator, Mapping
from typing import Any

from dc_core.params import param
from dc_core.qos import RECORD_HISTORY_DEPTH

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


def topic_param(default: Any = dataclasses.MISSING, *, doc: str) -> Any:
    """A plugin parameter naming a robot topic it reads, refused at configure when no mapping makes it one
    (no default: required); under --namespace, an absolute one outside it is warned about (sensor_topic)."""
    return param(default, doc=doc, check=lambda name: topic_problem(name) and "a ROS 2 topic name", sensor_topic=True)


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


# The default names of the topics DC's servers publish on, relative like the prefixes above. Each server
# uses these functions, and so does the destination server, which reads the others' sections to learn
# which of its inputs are DC's own (published_topics below): a name changes here, once.
def measurement_topic(measurement_id: str) -> str:
    """The output topic of a measurement whose ``topic_output`` is not given (before resolution)."""
    return MEASUREMENT_TOPIC_PREFIX + measurement_id


def group_topic(group: str) -> str:
    """The output topic of a group whose ``output`` is not given (before resolution)."""
    return GROUP_TOPIC_PREFIX + group


def condition_topic(condition: str) -> str:
    """The topic a condition's state is published on (before resolution)."""
    return CONDITION_TOPIC_PREFIX + condition


def published_topics(servers: Mapping[str, Any], namespace: str = "/") -> tuple[dict[str, int], list[str]]:
    """The topics the measurement and group servers of one parameter file publish, fully qualified as
    those servers in ``namespace`` resolve them, each with the depth of the history it keeps; and, as
    warnings, what could not be read.

    Read from the sections' few keys that name a topic, not by the servers' configuration classes: the
    destination server learns its siblings' topics without importing them. dc-bringup validated the
    file with those classes first; what does not read here is taken as another node's topic, and said.
    """
    topics: dict[str, int] = {}
    problems: list[str] = []
    # A server's section is named after its node, the name ``~`` and ``{node}`` resolve to.
    for mid, body, path, node in _listed_sections(servers, "measurement_server", "measurement_plugins", problems):
        topic = body.get("topic_output") or measurement_topic(mid)
        depth = body.get("history_depth", RECORD_HISTORY_DEPTH)
        if not isinstance(topic, str):
            problems.append(f"{path}.topic_output: not a topic name, its records are taken as another node's")
        elif isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
            problems.append(f"{path}.history_depth: not a depth, its records are taken as another node's")
        else:
            topics[resolve_topic(topic, namespace, node)] = depth
    for group, body, path, node in _listed_sections(servers, "group_server", "groups", problems):
        topic = body.get("output") or group_topic(group)
        if isinstance(topic, str):
            topics[resolve_topic(topic, namespace, node)] = RECORD_HISTORY_DEPTH
        else:
            problems.append(f"{path}.output: not a topic name, its records are taken as another node's")
    return topics, problems


def _listed_sections(
    servers: Mapping[str, Any], server: str, key: str, problems: list[str]
) -> Iterator[tuple[str, Mapping[str, Any], str, str]]:
    """(id, section, YAML path, node name) of each plugin or group ``server`` lists under ``key``."""
    section = servers.get(server)
    if section is None:
        return
    listed = section.get(key, []) if isinstance(section, Mapping) else None
    if not isinstance(listed, list):
        problems.append(f"{server}.{key}: not a list, the topics of {server} are taken as other nodes'")
        return
    for name in listed:
        body = section.get(name) if isinstance(name, str) else None
        if isinstance(body, Mapping):
            yield name, body, f"{server}.{name}", server
        else:
            problems.append(f"{server}.{name}: no section, its records are taken as another node's")
