"""Parameters of the destination server: node level (with the ``flb`` delivery section) and per destination.

Parsing is pure: it loads plugin classes through their entry points and checks every value, but
opens no file and connects to nothing. ``dc validate`` and ``dc-bringup`` call it before anything runs.
A destination section is checked against three parameter classes at once — the common ones below,
the delivery ones of :mod:`dc_destinations.settings` and the plugin's own ``Params`` — so an unknown
key is reported once, with a suggestion taken from all of them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any

from dc_core.errors import ConfigError
from dc_core.node_params import ServerNodeParams, record_linger_param
from dc_core.params import did_you_mean, field_names, no_effect_notes, param, parse_params
from dc_core.plugins import parse_plugin_section
from dc_core.timefmt import TIME_FORMATS
from dc_core.topics import resolve_topic
from dc_destinations.health import DEFAULT_UNHEALTHY_AFTER_S
from dc_destinations.settings import (
    DeliveryParams,
    DestinationDeliveryParams,
    check_destination_params,
    link_rates,
    record_priorities,
    time_key_param,
)

# Keys of the original's Fluent Bit input plumbing: meaningless without Fluent Bit, harmless to accept.
NODE_NAME = "destination_server"
_OBSOLETE_NODE_KEYS = ("ros2_plugin_path", "ros2_plugin_spin_time_ms")
# Written in destination_server by the seed's TurtleBot3 stdout demo; the original ignored them there.
_MEASUREMENT_SERVER_KEYS = ("custom_str_params_list", "custom_str_params")
TRUST_TAGS_FROM = ("dc_servers", "any")
# Spellings of `flb` keys found in the seed's examples, with the key DC reads instead.
_FLB_RENAMED = {"flb_grace": "grace", "metrics": "http_server"}


@dataclass(frozen=True, kw_only=True)
class DestinationServerParams(ServerNodeParams):
    # Longer than the other servers': nothing here is timed finer than a heartbeat, and a record
    # spends up to flb.commit_interval (0.05 s) in memory before its group commit anyway. At 1,000
    # records/s it costs a third less CPU per record than 0.01 s (docs/performance.md).
    record_linger: float = record_linger_param(0.05)
    destination_plugins: list[str] = param([], doc="Names of the destinations to load, each with its section")
    flb: DeliveryParams = param(default_factory=DeliveryParams, doc="Delivery settings (Fluent Bit's names)")
    trust_tags_from: str = param(
        "dc_servers",
        choices=TRUST_TAGS_FROM,
        doc="Whose records on /dc/measurement/* and /dc/group/* may reach file destinations by their tags "
        "(dc_servers: DC's measurement and group servers only; any: every publisher)",
    )
    unhealthy_after: float = param(
        DEFAULT_UNHEALTHY_AFTER_S,
        minimum=0.1,
        doc="Seconds without a successful send before a destination is reported failing (each destination may"
        " set its own)",
    )


@dataclass(frozen=True, kw_only=True)
class DestinationCommonParams:
    plugin: str = param(doc="Plugin type, e.g. dc_destinations/Stdout")
    inputs: list[str] = param(doc="Topics this destination takes records from (StringStamped)")
    debug: bool = param(False, doc="Log every record routed to this destination")
    time_format: str = param(
        "double", choices=TIME_FORMATS, aliases=("json_date_format",), doc="Format of the time key"
    )
    time_key: str = time_key_param("Key receiving the record's header stamp (empty: no time key)")


@dataclass(frozen=True)
class DestinationConfig:
    name: str
    common: DestinationCommonParams
    delivery: DestinationDeliveryParams
    plugin_class: type
    plugin_params: Any


@dataclass(frozen=True)
class DestinationServerConfig:
    node: DestinationServerParams
    destinations: list[DestinationConfig]
    warnings: list[str] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        return [d.name for d in self.destinations]

    @property
    def inputs(self) -> set[str]:
        return {topic for d in self.destinations for topic in d.common.inputs}


def _numeric_strings_to_numbers(values: dict[str, Any], cls: type) -> dict[str, Any]:
    """The seed documents the `flb` numbers as strings ("1", "2000"); read them as the numbers they are."""
    hints = typing.get_type_hints(cls)
    out = dict(values)
    for key, value in values.items():
        if not isinstance(value, str) or hints.get(key) not in (int, float):
            continue
        # A non-number is left as is: parse_params reports it with the expected type.
        with contextlib.suppress(ValueError):
            out[key] = int(value) if hints[key] is int else float(value)
    return out


def _flb_section(section: dict[str, Any], path: str, warnings: list[str]) -> dict[str, Any]:
    raw = section.get("flb", {})
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}.flb", f"expected a mapping, got {raw!r}")
    flb = dict(raw)
    for old, new in _FLB_RENAMED.items():
        if old not in flb:
            continue
        value = flb.pop(old)
        if new in flb:
            warnings.append(f"{path}.flb.{old}: ignored, {path}.flb.{new} is set too")
            continue
        warnings.append(f"{path}.flb.{old} is a deprecated spelling of {path}.flb.{new}")
        flb[new] = value
    # The seed's demos put `flb_grace` next to `flb` when the YAML indentation is read literally.
    if "flb_grace" in section:
        if "grace" in flb:
            warnings.append(f"{path}.flb_grace: ignored, {path}.flb.grace is set too")
        else:
            warnings.append(f"{path}.flb_grace is a deprecated spelling of {path}.flb.grace")
            flb["grace"] = section["flb_grace"]
    return _numeric_strings_to_numbers(flb, DeliveryParams)


def _parse_destination(
    name: str, body: Any, path: str, namespace: str, warnings: list[str], links: dict[str, str]
) -> DestinationConfig:
    if body is None:
        raise ConfigError(path, "section missing (listed in destination_plugins but not configured)")
    if not isinstance(body, dict):
        raise ConfigError(path, f"expected a mapping, got {body!r}")
    parsed = parse_plugin_section(
        "destinations", body, path, DestinationCommonParams, shared=(DestinationDeliveryParams,)
    )
    common, plugin_class, plugin_params = parsed.common, parsed.plugin_class, parsed.params
    (delivery,) = parsed.shared
    warnings.extend(parsed.notes)
    check_destination_params(delivery, path, links)
    if not common.inputs:
        raise ConfigError(f"{path}.inputs", "expected at least one topic")
    for i, topic in enumerate(common.inputs):
        if not topic:
            raise ConfigError(f"{path}.inputs[{i}]", "expected a topic name, got an empty string")
    # Fully qualified as the server subscribes: records keep the topic they came on, and routing,
    # hand-off acks and the checks against the other sections' outputs compare these names.
    common = dataclasses.replace(common, inputs=[resolve_topic(t, namespace, NODE_NAME) for t in common.inputs])
    if delivery.retention_priorities:
        # Topic keys resolved as the inputs are: the pipeline compares them with the records' topics.
        priorities = record_priorities(
            delivery, common.inputs, path, lambda key: resolve_topic(key, namespace, NODE_NAME)
        )
        delivery = dataclasses.replace(delivery, retention_priorities=priorities)
    return DestinationConfig(name, common, delivery, plugin_class, plugin_params)


def parse_destination_server(
    section: dict[str, Any], path: str = "destination_server", namespace: str = "/"
) -> DestinationServerConfig:
    warnings: list[str] = []
    node_keys = field_names(DestinationServerParams)
    node_values = {key: section[key] for key in node_keys if key in section}
    node_values["flb"] = _flb_section(section, path, warnings)
    node = parse_params(DestinationServerParams, node_values, path)
    link_rates(node.flb, f"{path}.flb")
    warnings.extend(no_effect_notes(DestinationServerParams, node_values, path))

    seen: set[str] = set()
    for name in node.destination_plugins:
        if name in seen:
            raise ConfigError(f"{path}.destination_plugins", f"{name!r} is listed twice")
        seen.add(name)
        if name in node_keys or name == "flb_grace" or name in _OBSOLETE_NODE_KEYS:
            raise ConfigError(f"{path}.destination_plugins", f"{name!r} is a server parameter, not a name")
    if not node.destination_plugins:
        warnings.append(f"{path}.destination_plugins is empty: records are delivered nowhere")

    destinations = [
        _parse_destination(name, section.get(name), f"{path}.{name}", namespace, warnings, node.flb.links)
        for name in node.destination_plugins
    ]
    # A destination without its own unhealthy_after has the server's.
    destinations = [
        d
        if d.delivery.unhealthy_after
        else dataclasses.replace(d, delivery=dataclasses.replace(d.delivery, unhealthy_after=node.unhealthy_after))
        for d in destinations
    ]

    for key in section:
        if key in node_keys or key in seen or key == "flb_grace":
            continue
        if key in _OBSOLETE_NODE_KEYS:
            warnings.append(f"{path}.{key} has no effect in DC (it set up the original's Fluent Bit input)")
            continue
        if key in _MEASUREMENT_SERVER_KEYS:
            warnings.append(f"{path}.{key}: ignored, it is a measurement_server parameter (its records carry them)")
            continue
        body = section[key]
        if isinstance(body, dict) and "plugin" in body:
            # The seed's reference configuration keeps sections of disabled destinations around.
            warnings.append(f"{path}.{key}: destination section not listed in destination_plugins, ignored")
            continue
        options = node_keys | set(node.destination_plugins)
        raise ConfigError(
            f"{path}.{key}",
            "unknown parameter (a destination section must be listed in destination_plugins)"
            + did_you_mean(str(key), options),
        )
    return DestinationServerConfig(node, destinations, warnings)
