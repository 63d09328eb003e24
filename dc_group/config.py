"""Parameters of the group server: the list of groups and, per group, its inputs and output record.

Parsing is pure (no I/O): ``dc validate`` and ``dc-bringup`` call it before anything starts.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from dc_core.errors import ConfigError
from dc_core.handoff import HandoffParams
from dc_core.node_params import MetricsHttpParams, ServerNodeParams, http_port_param
from dc_core.params import did_you_mean, param, parse_params
from dc_core.record_history import DEFAULT_HISTORY_BYTES
from dc_core.topics import group_topic, resolve_topic

NODE_NAME = "group_server"
# How long past the slop an incomplete set is kept when sync_timeout is not set: the latest
# partner of a message is stamped at most sync_delay after it, and this leaves room for
# collection and transport delays.
TIMEOUT_MARGIN_S = 1.0
# Standard ROS parameters that may sit in any node's section; accepted and not used.


@dataclass(frozen=True, kw_only=True)
class GroupServerParams(ServerNodeParams, MetricsHttpParams):
    groups: list[str] = param(doc="Ids of the groups to enable; each has a section of the same name")
    handoff: HandoffParams = param(
        default_factory=HandoffParams, doc="Records kept until destination_server acknowledges them"
    )
    http_port: int = http_port_param(2021)


@dataclass(frozen=True, kw_only=True)
class GroupParams:
    inputs: list[str] = param(doc="StringStamped topics to merge (measurement or group outputs)")
    output: str = param("", doc="Topic of the merged records (default dc/group/<group>, in the server's namespace)")
    sync_delay: float = param(
        5.0, minimum=0.0, doc="Slop in seconds: the largest spread of header stamps within one set"
    )
    sync_timeout: float | None = param(
        None,
        doc="Seconds a message waits for its partners before its set is incomplete "
        f"(default sync_delay + {TIMEOUT_MARGIN_S:g})",
    )
    on_sync_timeout: str = param("drop", choices=("drop", "emit_partial"), doc="What happens to an incomplete set")
    queue_size: int = param(10, minimum=1, doc="Pending messages kept per input; the oldest goes first")
    group_key: str = param("", doc="StringStamped.group_key of the output (default the group id)")
    exclude_keys: list[str] = param(
        [], doc="Key paths removed from the merged record, '.'-separated, '*' matches one key"
    )
    tags: list[str] = param([], doc="Destination names the merged record is routed to")
    nested_data: bool = param(True, doc="Publish nested objects; false flattens keys with '.'")
    include_group_name: bool = param(True, doc='Add "name": <group id>')
    history_bytes: int = param(
        DEFAULT_HISTORY_BYTES,
        minimum=0,
        doc="Bytes of merged records the output topic keeps at most (its 1,000 records' depth shrinks to fit "
        "the largest record, never below 1); 0: no byte bound",
    )


@dataclass(frozen=True, kw_only=True)
class GroupConfig:
    """One group, with its defaults resolved."""

    name: str
    inputs: tuple[str, ...]
    output: str
    sync_delay: float
    sync_timeout: float
    emit_partial: bool
    queue_size: int
    group_key: str
    exclude_keys: tuple[str, ...]
    tags: tuple[str, ...]
    nested_data: bool
    include_group_name: bool
    history_bytes: int


@dataclass(frozen=True, kw_only=True)
class GroupServerConfig:
    node: GroupServerParams
    groups: tuple[GroupConfig, ...]
    warnings: list[str] = field(default_factory=list)

    @property
    def inputs(self) -> set[str]:
        """Every topic the server subscribes to."""
        return {topic for group in self.groups for topic in group.inputs}

    @property
    def outputs(self) -> set[str]:
        """Every topic the server publishes merged records on."""
        return {group.output for group in self.groups}

    @property
    def tags(self) -> dict[str, list[str]]:
        """Output topic -> the tags its records carry."""
        return {group.output: list(group.tags) for group in self.groups}


def parse_group_server(section: dict[str, Any], path: str = "group_server", namespace: str = "/") -> GroupServerConfig:
    """Build the group server configuration from its ``ros__parameters`` mapping; topic names come out
    fully qualified, as the server in ``namespace`` resolves them."""
    if not isinstance(section, dict):
        raise ConfigError(path, f"expected a mapping, got {section!r}")
    node_keys = tuple(f.name for f in fields(GroupServerParams))
    node = parse_params(GroupServerParams, {k: v for k, v in section.items() if k in node_keys}, path)
    names = list(node.groups)
    for i, name in enumerate(names):
        if not name:
            raise ConfigError(f"{path}.groups[{i}]", "a group id cannot be empty")
        if name in node_keys:
            raise ConfigError(f"{path}.groups[{i}]", f'"{name}" is a server parameter, not a group id')
        if name in names[:i]:
            raise ConfigError(f"{path}.groups[{i}]", f'group "{name}" is listed twice')
    for key in section:
        if key not in node_keys and key not in names:
            hint = did_you_mean(str(key), [*node_keys, *names])
            raise ConfigError(f"{path}.{key}", f"unknown parameter (not a group listed in {path}.groups){hint}")
    groups = tuple(_parse_group(name, section.get(name), f"{path}.{name}", namespace) for name in names)
    _check_topology(groups, path)
    warnings = [
        f"{path}.{g.name}: sync_timeout ({g.sync_timeout:g} s) is shorter than sync_delay "
        f"({g.sync_delay:g} s): sets spread wider than the timeout never complete"
        for g in groups
        if g.sync_timeout < g.sync_delay
    ]
    return GroupServerConfig(node=node, groups=groups, warnings=warnings)


def _parse_group(name: str, section: Any, path: str, namespace: str) -> GroupConfig:
    if section is None:
        raise ConfigError(path, "group section missing (a listed group needs at least its inputs)")
    params = parse_params(GroupParams, section, path)
    if not params.inputs:
        raise ConfigError(f"{path}.inputs", "expected at least one input topic")
    inputs: list[str] = []
    for i, topic in enumerate(params.inputs):
        if not topic.strip():
            raise ConfigError(f"{path}.inputs[{i}]", "a topic name cannot be empty")
        resolved = resolve_topic(topic, namespace, NODE_NAME)
        if resolved in inputs:
            raise ConfigError(f"{path}.inputs[{i}]", f"{resolved} is listed twice")
        inputs.append(resolved)
    if params.sync_timeout is not None and params.sync_timeout <= 0:
        raise ConfigError(f"{path}.sync_timeout", f"expected a number > 0, got {params.sync_timeout!r}")
    timeout = params.sync_timeout if params.sync_timeout is not None else params.sync_delay + TIMEOUT_MARGIN_S
    for i, pattern in enumerate(params.exclude_keys):
        if not pattern or any(part == "" for part in pattern.split(".")):
            raise ConfigError(f"{path}.exclude_keys[{i}]", f'expected "key.sub.key" paths, got "{pattern}"')
    return GroupConfig(
        name=name,
        inputs=tuple(inputs),
        output=resolve_topic(params.output or group_topic(name), namespace, NODE_NAME),
        sync_delay=params.sync_delay,
        sync_timeout=timeout,
        emit_partial=params.on_sync_timeout == "emit_partial",
        queue_size=params.queue_size,
        group_key=params.group_key or name,
        exclude_keys=tuple(params.exclude_keys),
        tags=tuple(params.tags),
        nested_data=params.nested_data,
        include_group_name=params.include_group_name,
        history_bytes=params.history_bytes,
    )


def _check_topology(groups: tuple[GroupConfig, ...], path: str) -> None:
    """Outputs are unique and no group feeds itself, directly or through other groups."""
    producer: dict[str, str] = {}
    for group in groups:
        if group.output in producer:
            raise ConfigError(
                f"{path}.{group.name}.output",
                f"{group.output} is already the output of group {producer[group.output]}",
            )
        producer[group.output] = group.name
    feeds = {g.name: [producer[t] for t in g.inputs if t in producer] for g in groups}

    def visit(name: str, trail: list[str]) -> None:
        if name in trail:
            # The trail follows "takes its input from"; reversed, it reads in the direction records flow.
            loop = " -> ".join(reversed([*trail[trail.index(name) :], name]))
            raise ConfigError(f"{path}.{trail[-1]}.inputs", f"groups feed each other in a loop: {loop}")
        for upstream in feeds[name]:
            visit(upstream, [*trail, name])

    for group in groups:
        visit(group.name, [])
