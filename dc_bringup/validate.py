"""Whole-configuration checks shared by ``dc validate`` and ``dc-bringup`` (no I/O but the file read)."""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dc_core.config import load_params
from dc_core.errors import ConfigError
from dc_core.params import did_you_mean
from dc_core.ros_args import param_sections, topic_remaps
from dc_core.topics import outside_namespace, resolve_topic, ros_namespace, ros_topic

# Servers in start order: destinations first so nothing published at start is lost.
# In start order: destinations first (nothing published at start is lost), measurements last.
SERVER_MODULES = {
    "destination_server": "dc_destinations.server",
    "group_server": "dc_group.server",
    "image_services": "dc_measurements.image_services",
    "measurement_server": "dc_measurements.server",
}
_PARSERS = {
    "destination_server": ("dc_destinations.config", "parse_destination_server"),
    "group_server": ("dc_group.config", "parse_group_server"),
    "image_services": ("dc_measurements.image_services", "parse_image_services"),
    "measurement_server": ("dc_measurements.config", "parse_measurement_server"),
}


@dataclass
class ValidationReport:
    servers: list[str] = field(default_factory=list)
    configs: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # said once at INFO, not warnings


# The servers whose topic names resolve in their namespace (image_services' are services).
_TOPIC_SERVERS = ("destination_server", "group_server", "measurement_server")


def _parse(server: str, section: dict[str, Any], namespace: str) -> Any:
    module_name, function = _PARSERS[server]
    module = importlib.import_module(module_name)
    if server in _TOPIC_SERVERS:
        return getattr(module, function)(section, server, namespace)
    return getattr(module, function)(section, server)


def validate_params_file(
    path: str | Path, namespace: str = "", ros_args: Sequence[str] = (), environ: Mapping[str, str] | None = None
) -> ValidationReport:
    """Parse every server section as the servers in ``namespace`` read it (topic names fully qualified
    there, the ``--ros-args`` parameters over the file's); raise ConfigError on the first error, return warnings.
    ``environ``: what ``${NAME}`` references read (the process' environment by default)."""
    loaded = load_params(path, namespace, param_sections(ros_args), environ)
    sections = loaded.servers
    report = ValidationReport()
    if loaded.ignored:
        report.notes.append(
            "sections for nodes DC does not run, ignored (other nodes' parameters): " + ", ".join(loaded.ignored)
        )
    for server in SERVER_MODULES:
        if server in sections:
            config = _parse(server, sections[server], ros_namespace(namespace))
            report.servers.append(server)
            report.configs[server] = config
            report.warnings.extend(getattr(config, "warnings", []))
    report.warnings.extend(_cross_checks(report.configs))
    report.warnings.extend(_robot_free_paths(report.configs))
    ns = ros_namespace(namespace)
    report.warnings.extend(_shared_root_topics(report.configs, ns))
    report.warnings.extend(_shared_root_services(report.configs, ns))
    report.warnings.extend(_sensor_topics_outside(report.configs, sections.get("measurement_server", {}), ns, ros_args))
    return report


def _names_the_robot(path: str, robot_ids: set[str]) -> bool:
    """Whether a path template holds something that differs per robot: a custom parameter naming the
    robot (``=robot_name``), an environment variable with ROBOT in its name, or a literal folder
    (taken for the robot's name: DC cannot tell it from another word)."""
    for part in path.split("/"):
        if not part or "%" in part:
            continue
        if part.startswith("="):
            if part[1:] in robot_ids:
                return True
            continue
        if "$" in part:
            if "ROBOT" in part.upper():
                return True
            continue
        return True
    return False


def _robot_free_paths(configs: dict[str, Any]) -> list[str]:
    """Measurements whose uploaded files' keys (all_base_path/<remote prefix>/…) and local paths
    (save_local_base_path/all_base_path/…) hold nothing that tells robots apart: several robots writing
    to one bucket overwrite each other's objects when they save in the same second."""
    measurements = configs.get("measurement_server")
    if measurements is None:
        return []
    robot_ids = {cid for cid, p in measurements.custom_str_params.items() if "robot" in p.name.lower()}
    robot_ids |= {p.name for p in measurements.custom_str_params.values() if "robot" in p.name.lower()}
    base = measurements.node.all_base_path
    if _names_the_robot(base, robot_ids):
        return []
    colliding = [
        m.name
        for m in measurements.measurements
        if m.common.remote_keys and not any(_names_the_robot(prefix, robot_ids) for prefix in m.common.remote_prefixes)
    ]
    if not colliding:
        return []
    return [
        f"measurement_server.all_base_path: {base!r} holds no robot name, nor do the remote_prefixes of "
        f"{', '.join(colliding)}: the object keys (and files_metrics' local paths) of several robots sharing "
        "a bucket can collide, and a robot overwrites another's file saved in the same second; start "
        'all_base_path with the robot\'s name, e.g. "=robot_name/%Y/%m/%d/%H" with a custom_str_params entry '
        "robot_name (docs/data-model.md)"
    ]


def _shared_root_services(configs: dict[str, Any], namespace: str) -> list[str]:
    """image_services' service_namespace written absolute outside the namespace: every DC of the domain
    offering it serves the same services (the last one started answers)."""
    if namespace == "/" or "image_services" not in configs:
        return []
    written = configs["image_services"].node.service_namespace
    resolved = resolve_topic(written, namespace, "image_services")
    if resolved == namespace or resolved.startswith(namespace + "/"):
        return []
    return [
        f"image_services.service_namespace: {written} is absolute: outside namespace {namespace}, the same "
        f"services for every DC of this ROS domain; write {written.strip('/')} (relative) for this DC's own"
    ]


def _sensor_topics_outside(
    configs: dict[str, Any], section: dict[str, Any], namespace: str, ros_args: Sequence[str]
) -> list[str]:
    """The robot's topics DC reads (parameters marked ``sensor_topic``: ``/odom``, ``/map``, …) that are
    absolute and outside the namespace, defaults included: once per topic, with the parameters naming it.

    They stay absolute (the original's defaults, which files rely on), but under --namespace they are
    most often another robot's or nobody's: Nav2's multi-robot bringup puts them in the namespace. A
    name a ``-r`` rule sends elsewhere is the user's choice and not warned about.
    """
    if namespace == "/" or "measurement_server" not in configs:
        return []
    measurements = configs["measurement_server"]
    remaps = topic_remaps(ros_args, namespace, "measurement_server")
    named = [(m.name, m.plugin_params) for m in measurements.measurements]
    named += [(cid, c.plugin_params) for cid, c in measurements.conditions.items()]
    uses: dict[str, list[tuple[str, str, bool]]] = {}  # topic -> (YAML path, key, whether the default)
    for name, params in named:
        written = section.get(name)
        if not dataclasses.is_dataclass(params) or not isinstance(written, dict):
            continue
        for f in dataclasses.fields(params):
            value = getattr(params, f.name)
            if not f.metadata.get("sensor_topic") or not isinstance(value, str) or not value:
                continue
            topic = resolve_topic(ros_topic(value), namespace, "measurement_server")
            if topic in remaps or topic.startswith(namespace + "/"):
                continue
            path = f"measurement_server.{name}.{f.name}"
            default = not any(key in written for key in (f.name, *f.metadata.get("aliases", ())))
            uses.setdefault(topic, []).append((path, f.name, default))
    warnings = []
    for topic, where in uses.items():
        relative = topic.lstrip("/")
        paths = ", ".join(path + (" (default)" if default else "") for path, _, default in where)
        fixes = " or ".join(f"{key}: {relative}" for key in dict.fromkeys(key for _, key, _ in where))
        warnings.append(
            f"{topic} is absolute: outside namespace {namespace}, not this robot's own topic ({paths}); "
            f"write {fixes} (relative: {namespace}/{relative}) for this robot's, or remap it "
            f"(--ros-args -r {topic}:={relative})"
        )
    return warnings


def _shared_root_topics(configs: dict[str, Any], namespace: str) -> list[str]:
    """DC topic names written absolute (/dc/…) while the servers run in a namespace: once per name,
    for they are not isolated — every DC of the ROS domain publishes or reads the same topic."""
    named: list[str] = []
    if "measurement_server" in configs:
        measurements = configs["measurement_server"]
        named += [m.output_topic for m in measurements.measurements]
        named += [c.common.topic for c in measurements.conditions.values() if c.common.topic]
    if "group_server" in configs:
        for group in configs["group_server"].groups:
            named += [*group.inputs, group.output]
    if "destination_server" in configs:
        named += [topic for d in configs["destination_server"].destinations for topic in d.common.inputs]
    return [
        f"{topic} is absolute: outside namespace {namespace}, shared with every DC of this ROS domain; "
        f"write {topic.lstrip('/')} (relative) for this DC's own"
        for topic in outside_namespace(named, namespace)
    ]


def _cross_checks(configs: dict[str, Any]) -> list[str]:
    warnings: list[str] = []
    measurements = configs.get("measurement_server")
    groups = configs.get("group_server")
    destinations = configs.get("destination_server")

    published: dict[str, str] = {}
    tagged: list[tuple[str, list[str]]] = []
    if measurements is not None:
        for m in measurements.measurements:
            source = getattr(m.plugin_params, "topic", None)
            if isinstance(source, str) and ros_topic(source) != source:
                warnings.append(
                    f"measurement_server.{m.name}.topic: {source!r} is not a valid ROS 2 topic name; "
                    f"DC listens on {ros_topic(source)!r}"
                )
            published[m.output_topic] = f"measurement_server.{m.name}"
            tagged.append((f"measurement_server.{m.name}.tags", list(m.common.tags)))
    if groups is not None:
        for topic in groups.outputs:
            published[topic] = "group_server"
        for topic, tags in groups.tags.items():
            tagged.append((f"group_server (output {topic}) tags", list(tags)))
        for topic in sorted(groups.inputs):
            if topic not in published:
                warnings.append(
                    f"group_server: input {topic} is published by nothing in this configuration"
                    + did_you_mean(topic, published)
                )

    if destinations is not None:
        names = set(destinations.names)
        for dest in destinations.destinations:
            for topic in dest.common.inputs:
                if topic not in published:
                    warnings.append(
                        f"destination_server.{dest.name}.inputs: {topic} is published by nothing in this "
                        "configuration (fine if another node publishes it)" + did_you_mean(topic, published)
                    )
        for where, tags in tagged:
            for tag in tags:
                if tag and tag not in names:
                    warnings.append(f"{where}: {tag!r} names no destination" + did_you_mean(tag, names))
    elif tagged and any(tags for _, tags in tagged):
        warnings.append("records are tagged but there is no destination_server section: they go nowhere")
    warnings.extend(_shared_metrics_ports(configs))
    return warnings


@dataclass(frozen=True)
class MetricsEndpoint:
    """Where a server of the configuration serves its counters (its http_server is true)."""

    server: str
    path: str  # of its http_* parameters, for messages
    listen: str
    port: int


def metrics_endpoints(configs: dict[str, Any]) -> list[MetricsEndpoint]:
    """The metrics HTTP servers a parsed configuration enables, in start order."""
    settings = {
        "destination_server": ("destination_server.flb", lambda c: c.node.flb),
        "group_server": ("group_server", lambda c: c.node),
        "measurement_server": ("measurement_server", lambda c: c.node),
    }
    endpoints = []
    for server, (path, http_settings) in settings.items():
        if server in configs:
            node = http_settings(configs[server])
            if node.http_server:
                endpoints.append(MetricsEndpoint(server, path, node.http_listen, node.http_port))
    return endpoints


def _shared_metrics_ports(configs: dict[str, Any]) -> list[str]:
    """Two servers whose metrics HTTP servers would bind the same port: the second one fails to."""
    enabled = metrics_endpoints(configs)
    warnings = []
    for i, endpoint in enumerate(enabled):
        for other in enabled[:i]:
            wildcard = "0.0.0.0" in (endpoint.listen, other.listen) or "" in (endpoint.listen, other.listen)
            if endpoint.port != 0 and endpoint.port == other.port and (endpoint.listen == other.listen or wildcard):
                warnings.append(
                    f"{endpoint.path}.http_port: {endpoint.port} is also {other.path}.http_port: {endpoint.server} "
                    "serves its metrics on another, free port (dc status finds it)"
                )
    return warnings


def check(
    path: str | Path, namespace: str = "", ros_args: Sequence[str] = ()
) -> tuple[ValidationReport | None, str | None]:
    """(report, None) when valid, (None, error text) when not."""
    try:
        return validate_params_file(path, namespace, ros_args), None
    except ConfigError as exc:
        return None, str(exc)
