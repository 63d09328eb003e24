"""Parameters of the measurement server: node level, per measurement, per condition.

Parsing is pure: it loads plugin classes through their entry points and checks every value, but
opens no file and starts nothing. ``dc validate`` and ``dc-bringup`` call it before anything runs.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dc_core.errors import ConfigError, DcError
from dc_core.handoff import HandoffParams
from dc_core.jsonpath import impossible_path, schema_types_at
from dc_core.node_params import MetricsHttpParams, ServerNodeParams, http_port_param
from dc_core.params import did_you_mean, field_names, param, parse_params
from dc_core.paths import DEFAULT_SAVE_BASE_PATH, PATHS_TIMEZONES, expand_env, expand_values, zone_problem
from dc_core.plugins import parse_plugin_section
from dc_core.qos import RECORD_HISTORY_DEPTH
from dc_core.record_history import DEFAULT_HISTORY_BYTES
from dc_core.topics import measurement_topic, resolve_topic

NODE_NAME = "measurement_server"
KEY_LAYOUTS = ("path", "hive")
# The custom string parameter whose value names the robot in Hive-style keys (robot=<name>/...).
ROBOT_NAME_PARAM = "robot_name"


@dataclass(frozen=True, kw_only=True)
class RunIdParams:
    enabled: bool = param(True, doc="Add a `run_id` (string) to every record")
    counter: bool = param(True, doc="Run id from a counter file incremented at every start")
    counter_path: str = param("$HOME/run_id", doc="Counter file ($ENV expanded)")
    uuid: bool = param(False, doc="Run id from a random UUID (exclusive with `counter`)")


@dataclass(frozen=True, kw_only=True)
class CustomStrParam:
    name: str = param(doc="JSON key added to every record")
    value: str = param("", doc="Fixed value (wins over value_from_file)")
    value_from_file: str = param("", doc="Read the value from this file (one trailing newline stripped)")
    force_override: bool = param(False, doc="Overwrite the key when the record already has it")


@dataclass(frozen=True, kw_only=True)
class MeasurementServerParams(ServerNodeParams, MetricsHttpParams):
    measurement_plugins: list[str] = param([], doc="Ids of the measurements to load")
    condition_plugins: list[str] = param([], doc="Ids of the conditions to load")
    save_local_base_path: str = param(
        DEFAULT_SAVE_BASE_PATH, doc="Local base folder for saved files ($ENV, =param, strftime)"
    )
    all_base_path: str = param("", doc="Prefix for local and remote paths ($ENV, =custom_param)")
    paths_timezone: str = param(
        "utc",
        check=zone_problem,
        doc=f"Zone of the strftime tokens of saved files' paths and object keys: {PATHS_TIMEZONES} "
        "(local: the original's behaviour)",
    )
    key_layout: str = param(
        "path",
        choices=KEY_LAYOUTS,
        doc="Object keys of saved files: path (all_base_path/remote prefix/save_path, the original's) or hive "
        "(remote prefix/robot=<robot_name>/date=YYYY-MM-DD/save_path)",
    )
    custom_str_params_list: list[str] = param([], doc="Ids of custom string parameters added to records")
    run_id: RunIdParams = param(default_factory=RunIdParams, doc="Run identifier")
    handoff: HandoffParams = param(
        default_factory=HandoffParams, doc="Records kept until destination_server acknowledges them"
    )
    http_port: int = http_port_param(2022)


@dataclass(frozen=True, kw_only=True)
class MeasurementCommonParams:
    plugin: str = param(doc="Plugin type, e.g. dc_measurements/Uptime")
    group_key: str = param("", doc="Copied into StringStamped.group_key; the group server nests under it")
    topic_output: str = param(
        "", doc="Output topic (default dc/measurement/<id> in the server's namespace: /dc/measurement/<id> without one)"
    )
    polling_interval: int = param(1000, minimum=100, doc="Milliseconds between two collections")
    debug: bool = param(False, doc="Log every published record at info level")
    enable_validator: bool = param(True, doc="Validate every record against the JSON schema")
    json_schema_path: str = param("", doc="Use this schema file instead of the plugin's")
    drop_invalid: bool = param(False, doc="Drop records that fail validation instead of publishing them")
    tags: list[str] = param([], doc="Destination names this record is routed to")
    init_collect: bool = param(True, doc="Collect once at activation instead of after a first interval")
    init_max_measurements: int = param(0, minimum=-1, doc="Samples published before conditions apply")
    condition_max_measurements: int = param(0, minimum=-1, doc="Samples per condition episode")
    include_measurement_name: bool = param(True, doc='Add "name": <id>')
    include_measurement_plugin: bool = param(False, doc='Add "plugin": <plugin type>')
    history_depth: int = param(
        RECORD_HISTORY_DEPTH,
        minimum=1,
        doc="Records the output topic keeps for a destination_server that (re)starts late",
    )
    history_bytes: int = param(
        DEFAULT_HISTORY_BYTES,
        minimum=0,
        doc="Bytes of records the output topic keeps at most: the depth shrinks to fit the largest record "
        "published (never below 1); 0: history_depth alone",
    )
    remote_keys: list[str] = param([], doc="Names of remote storages (file-saving plugins)")
    remote_prefixes: list[str] = param([], doc="Prefix per remote key, same order")
    nested: bool = param(False, doc="Wrap the record as {<id>: record}")
    flatten: bool = param(False, doc='Flatten to JSON-pointer keys ("/a/b")')
    if_all_conditions: list[str] = param([], doc="Publish only if all these conditions are active")
    if_any_conditions: list[str] = param([], doc="Publish only if one of these conditions is active")
    if_none_conditions: list[str] = param([], doc="Publish only if none of these conditions is active")


@dataclass(frozen=True, kw_only=True)
class ConditionCommonParams:
    plugin: str = param(doc="Plugin type, e.g. dc_conditions/Exist")
    topic: str = param("", doc="Judge the latest record of this StringStamped topic instead of the sample")


@dataclass(frozen=True)
class MeasurementConfig:
    name: str
    common: MeasurementCommonParams
    plugin_class: type
    plugin_params: Any
    namespace: str = "/"

    @property
    def output_topic(self) -> str:
        return output_topic(self.name, self.common, self.namespace)

    @property
    def conditions(self) -> list[str]:
        c = self.common
        return [*c.if_all_conditions, *c.if_any_conditions, *c.if_none_conditions]


def output_topic(measurement_id: str, common: MeasurementCommonParams, namespace: str = "/") -> str:
    """Fully qualified, as the server in ``namespace`` publishes it: what other sections name is compared with it."""
    return resolve_topic(common.topic_output or measurement_topic(measurement_id), namespace, NODE_NAME)


@dataclass(frozen=True)
class ConditionConfig:
    name: str
    common: ConditionCommonParams
    plugin_class: type
    plugin_params: Any


@dataclass(frozen=True)
class MeasurementServerConfig:
    node: MeasurementServerParams
    custom_str_params: dict[str, CustomStrParam]
    measurements: list[MeasurementConfig]
    conditions: dict[str, ConditionConfig]
    warnings: list[str] = field(default_factory=list)


def _plugin_section(section: dict[str, Any], name: str, path: str) -> dict[str, Any]:
    body = section.get(name)
    if body is None:
        raise ConfigError(f"{path}.{name}", "section missing (the plugin is listed but not configured)")
    if not isinstance(body, dict):
        raise ConfigError(f"{path}.{name}", "expected a mapping")
    return body


def _listed_custom_params(
    ids: list[Any], section: dict[str, Any], path: str, warnings: list[str]
) -> dict[str, CustomStrParam]:
    """The older spelling of custom string parameters, which the seed's robot demos still write:
    ``custom_str_params: ["robot_name"]`` lists ids, and each id's value is the string parameter of
    that name beside it (``robot_name: "C3PO"``), added to records under the id itself."""
    custom: dict[str, CustomStrParam] = {}
    for index, cid in enumerate(ids):
        if not isinstance(cid, str) or not cid:
            raise ConfigError(
                f"{path}.custom_str_params[{index}]", f"expected the id of a string parameter, got {cid!r}"
            )
        value = section.get(cid)
        if value is None:
            raise ConfigError(
                f"{path}.{cid}", "missing: listed in custom_str_params (older form), which takes its value from here"
            )
        if not isinstance(value, str) or not value:
            raise ConfigError(
                f"{path}.{cid}", f"expected a non-empty string (listed in custom_str_params), got {value!r}"
            )
        custom[cid] = CustomStrParam(name=cid, value=value)
    if custom:
        warnings.append(
            f"{path}.custom_str_params: a list of ids is the older spelling, read as custom_str_params_list: "
            f"{list(custom)} with custom_str_params.<id>: {{name: <id>, value: <{path}.<id>>}}"
        )
    return custom


def _value_names(text: str) -> set[str]:
    """The names a path refers to as ``=name`` (dc_core.paths.expand_values' syntax)."""
    names: set[str] = set()

    def note(name: str) -> str:
        names.add(name)
        return ""

    expand_values(text, note)
    return names


def parse_measurement_server(
    section: dict[str, Any], path: str = "measurement_server", namespace: str = "/"
) -> MeasurementServerConfig:
    node_params = parse_params(
        MeasurementServerParams, section, path, ignore=set(section) - field_names(MeasurementServerParams)
    )
    if node_params.run_id.enabled and node_params.run_id.counter and node_params.run_id.uuid:
        raise ConfigError(f"{path}.run_id", "choose one source for the run id: counter or uuid, not both")

    warnings: list[str] = []
    dynamic: set[str] = {"custom_str_params"}
    custom: dict[str, CustomStrParam] = {}
    raw_custom = section.get("custom_str_params", {}) or {}
    if isinstance(raw_custom, list):
        custom = _listed_custom_params(raw_custom, section, path, warnings)
        dynamic.update(custom)
        raw_custom = {}
    elif not isinstance(raw_custom, dict):
        raise ConfigError(f"{path}.custom_str_params", "expected a mapping (or the older list of ids)")
    for cid in node_params.custom_str_params_list:
        if cid in custom:
            continue  # given by the older list form already
        cpath = f"{path}.custom_str_params.{cid}"
        if cid not in raw_custom:
            raise ConfigError(cpath, "section missing (listed in custom_str_params_list)")
        custom[cid] = parse_params(CustomStrParam, raw_custom[cid], cpath)
        if not custom[cid].value and not custom[cid].value_from_file:
            raise ConfigError(cpath, "needs 'value' or 'value_from_file'")
    if node_params.key_layout == "hive" and ROBOT_NAME_PARAM not in custom:
        raise ConfigError(
            f"{path}.key_layout",
            f"hive keys start with robot=<name>: add a custom string parameter {ROBOT_NAME_PARAM} "
            f"(custom_str_params_list: [{ROBOT_NAME_PARAM}])",
        )
    for key in raw_custom:
        # `force_override` at this level is the original's global switch (never used there either).
        if key not in custom and key != "force_override":
            raise ConfigError(f"{path}.custom_str_params.{key}", "not listed in custom_str_params_list")

    dynamic.update(node_params.condition_plugins, node_params.measurement_plugins)
    conditions: dict[str, ConditionConfig] = {}
    for cid in node_params.condition_plugins:
        condition = parse_plugin_section(
            "conditions", _plugin_section(section, cid, path), f"{path}.{cid}", ConditionCommonParams
        )
        warnings.extend(condition.notes)
        conditions[cid] = ConditionConfig(cid, condition.common, condition.plugin_class, condition.params)

    measurements: list[MeasurementConfig] = []
    outputs: dict[str, str] = {}
    for mid in node_params.measurement_plugins:
        mpath = f"{path}.{mid}"
        measurement = parse_plugin_section(
            "measurements", _plugin_section(section, mid, path), mpath, MeasurementCommonParams
        )
        warnings.extend(measurement.notes)
        common, cls, plugin_params = measurement.common, measurement.plugin_class, measurement.params
        for key in ("if_all_conditions", "if_any_conditions", "if_none_conditions"):
            for cid in getattr(common, key):
                if cid not in conditions:
                    raise ConfigError(
                        f"{mpath}.{key}",
                        f"condition {cid!r} is not in condition_plugins{did_you_mean(cid, conditions)}",
                    )
        if len(common.remote_prefixes) < len(common.remote_keys):
            raise ConfigError(f"{mpath}.remote_prefixes", "needs one prefix per entry of remote_keys")
        config = MeasurementConfig(mid, common, cls, plugin_params, namespace)
        if config.output_topic in outputs:
            raise ConfigError(
                f"{mpath}.topic_output",
                f"{config.output_topic} is already the output of {outputs[config.output_topic]!r}",
            )
        outputs[config.output_topic] = mid
        measurements.append(config)

    named_by_save_path = _value_names(node_params.save_local_base_path)
    for name in sorted(named_by_save_path):
        if not isinstance(section.get(name), str):
            raise ConfigError(
                f"{path}.save_local_base_path",
                f"'={name}' names no string parameter of {path} (write {name}: <value> beside it)",
            )
    unknown = set(section) - field_names(MeasurementServerParams) - dynamic - named_by_save_path
    for key in sorted(unknown):
        if key == "destinations":
            # The seed's QR demo writes destinations.minio.bucket here; the original read it (in
            # Camera) and never used it. Refusing it would refuse the demo for a key without effect.
            warnings.append(
                f"{path}.destinations: ignored, as in the original (the bucket is the MinIO or S3 destination's)"
            )
            continue
        if key in custom and isinstance(section[key], str):
            # The older spelling's value (robot_name: "C3PO") left beside the newer sections, as in the
            # seed's QR demo: the value that counts is custom_str_params.<id>'s.
            warnings.append(
                f"{path}.{key}: ignored; only the older list form of custom_str_params takes its value from here, "
                f"{path}.custom_str_params.{key} gives it"
            )
            continue
        options = field_names(MeasurementServerParams) | set(node_params.measurement_plugins)
        raise ConfigError(
            f"{path}.{key}",
            "unknown parameter (a plugin section must be listed in measurement_plugins or condition_plugins)"
            + did_you_mean(key, options),
        )

    _refuse_impossible_conditions(measurements, conditions, path)
    users: dict[str, list[str]] = {}
    for m in measurements:
        for cid in dict.fromkeys(m.conditions):
            users.setdefault(cid, []).append(m.name)
    for cid, names in users.items():
        ccfg = conditions[cid]
        if len(names) > 1 and getattr(ccfg.plugin_class, "remembers_samples", False) and not ccfg.common.topic:
            warnings.append(
                f"{path}.{cid}: {ccfg.common.plugin} compares each sample with the previous one, and "
                f"{', '.join(names)} all use it: it will compare their samples with each other "
                "(configure one condition per measurement)"
            )
    for m in measurements:
        c = m.common
        if not m.conditions and c.init_max_measurements == -1:
            warnings.append(f"{path}.{m.name}: init_max_measurements is -1 and no condition is set: it never publishes")
    return MeasurementServerConfig(node_params, custom, measurements, conditions, warnings)


def _refuse_impossible_conditions(
    measurements: list[MeasurementConfig], conditions: dict[str, ConditionConfig], path: str
) -> None:
    """A condition on a key the measurement's schema rules out, or on a value of a type the condition
    never accepts, could never be active for it: the measurement would stay silent (or the condition
    be pointless) for ever, with nothing in the logs. Refused, naming the schema's keys."""
    for m in measurements:
        schema = _schema_of(m)
        if schema is None:
            continue
        for cid in dict.fromkeys(m.conditions):
            condition = conditions[cid]
            key = getattr(condition.plugin_params, "key", None)
            if condition.common.topic or not isinstance(key, str):
                continue  # it judges another topic's records, or no key of the sample
            reason = impossible_path(schema, key)
            if reason is None:
                wanted: frozenset[str] = getattr(condition.plugin_class, "value_types", frozenset())
                types = schema_types_at(schema, key)
                if wanted and types is not None and not wanted & types:
                    reason = (
                        f"the schema says {' or '.join(sorted(types))}; "
                        f"{condition.common.plugin} needs {' or '.join(sorted(wanted))}"
                    )
            if reason is not None:
                raise ConfigError(
                    f"{path}.{cid}.key",
                    f"{key!r}: {cid} could never be active for {m.name} ({reason})",
                )


def _schema_of(measurement: MeasurementConfig) -> dict[str, Any] | None:
    """The schema a measurement's samples follow, when one is known and readable."""
    try:
        if measurement.common.json_schema_path:
            loaded: dict[str, Any] = json.loads(Path(expand_env(measurement.common.json_schema_path)).read_text())
            return loaded
        schema: dict[str, Any] | None = measurement.plugin_class.load_schema()  # type: ignore[attr-defined]
        return schema
    except (OSError, ValueError, DcError):
        return None  # the server says what is wrong with it
