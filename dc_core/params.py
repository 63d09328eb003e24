"""Typed plugin and server parameters, declared once as frozen dataclasses.

A parameter is a dataclass field created with :func:`param`; its Python annotation is its type,
its default is its default, and its metadata carries the documentation and range checks. Parsing
is pure (no I/O) and reports the YAML path of the first offending key::

    @dataclass(frozen=True, kw_only=True)
    class DummyParams:
        record: str = param('{"message": "Hello from ROS 2 DC"}', doc="JSON object to publish")
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from typing import Any, TypeVar

from dc_core.errors import ConfigError

T = TypeVar("T")

_MISSING: Any = dataclasses.MISSING


def param(
    default: Any = _MISSING,
    *,
    doc: str,
    default_factory: Callable[[], Any] | Any = _MISSING,
    minimum: float | None = None,
    maximum: float | None = None,
    choices: Iterable[Any] | None = None,
    secret: bool = False,
    aliases: Iterable[str] = (),
    check: Callable[[Any], str | None] | None = None,
    sensor_topic: bool = False,
    no_effect: str = "",
    section: type | None = None,
) -> Any:
    """Declare one parameter. No default means the key is required.

    ``check`` is a pure function returning None when the value is acceptable, or what was
    expected ("an IPv4 address"): reported with the parameter's YAML path. ``sensor_topic`` marks a
    topic the robot publishes (``/odom``): under ``--namespace``, an absolute one outside the
    namespace is warned about (dc_bringup.validate).

    ``no_effect`` (why it has none) marks a key accepted so that the original's files load, but
    ignored: :func:`no_effect_notes` says so for each one a configuration gives. ``section`` is the
    parameter class a mapping value of the key is read as, when the key's type cannot say it
    (``tls: true`` or a ``tls:`` section): :func:`no_effect_notes` looks into it.
    """
    metadata = {
        "doc": doc,
        "minimum": minimum,
        "maximum": maximum,
        "choices": tuple(choices) if choices is not None else None,
        "secret": secret,
        "aliases": tuple(aliases),
        "check": check,
        "sensor_topic": sensor_topic,
        "no_effect": no_effect,
        "section": section,
    }
    # A secret stays out of the dataclass repr, so logging a parameter object never shows it.
    shown = not secret
    if default_factory is not _MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=metadata, repr=shown)
    if isinstance(default, list):
        frozen = list(default)
        return dataclasses.field(default_factory=lambda: list(frozen), metadata=metadata, repr=shown)
    return dataclasses.field(default=default, metadata=metadata, repr=shown)


def compat_param(default: Any, because: str, **options: Any) -> Any:
    """A key accepted so that the original's files load, without effect in DC: ``because`` says why
    (in its documentation, and in the configure warning of :func:`no_effect_notes`)."""
    return param(default, doc=f"Accepted for the original's files; no effect: {because}", no_effect=because, **options)


def port_problem(port: int | str) -> str | None:
    """A ``check`` of a TCP port: 1 to 65535 (digits in a string count, as the original's files wrote them)."""
    if isinstance(port, str):
        port = int(port) if port.strip().isdigit() else 0
    return None if 1 <= port <= 65535 else "a TCP port from 1 to 65535"


def host_problem(host: str) -> str | None:
    """A ``check`` of a host name or IP address: not empty, no white space, nothing of a URL (``/?#``)."""
    return None if host and not any(c.isspace() or c in "/?#" for c in host) else "a host name or IP address"


def host_param(server: str) -> Any:
    """The ``host`` parameter of a client of ``server`` (``"the MQTT broker"``): this machine unless told otherwise."""
    return param("127.0.0.1", check=host_problem, doc=f"Host name or IP address of {server}")


def url_host(host: str) -> str:
    """``host`` as a URL writes it: an IPv6 address in brackets (RFC 3986)."""
    return f"[{host}]" if ":" in host else host


@dataclasses.dataclass(frozen=True, kw_only=True)
class NoParams:
    """Parameters of a plugin that has none of its own."""


@dataclasses.dataclass(frozen=True)
class ParamInfo:
    """What a parameter is, for documentation and `dc list-plugins --params`."""

    name: str
    type_name: str
    default: Any
    required: bool
    doc: str
    secret: bool


_BOOL_WORDS = {"true": True, "on": True, "yes": True, "false": False, "off": False, "no": False}


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is list:
        (inner,) = typing.get_args(tp)
        return f"list of {_type_name(inner)}"
    if origin is dict:
        return "mapping"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "null"
    return {bool: "boolean", int: "integer", float: "number", str: "string"}.get(tp, getattr(tp, "__name__", str(tp)))


def _fmt(value: Any) -> str:
    return f'"{value}"' if isinstance(value, str) else repr(value)


def _coerce(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if value is None:
            value = {}
        return parse_params(tp, value, path)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for option in typing.get_args(tp):
            try:
                return _coerce(option, value, path)
            except ConfigError as exc:
                errors.append(exc)
        raise ConfigError(path, f"expected {_type_name(tp)}, got {_fmt(value)}")
    if tp is type(None):
        if value is None:
            return None
        raise ConfigError(path, f"expected null, got {_fmt(value)}")
    if origin is list:
        (inner,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(path, f"expected a {_type_name(tp)}, got {_fmt(value)}")
        return [_coerce(inner, item, f"{path}[{i}]") for i, item in enumerate(value)]
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(path, f"expected a mapping, got {_fmt(value)}")
        return dict(value)
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in _BOOL_WORDS:
            return _BOOL_WORDS[value.strip().lower()]
        raise ConfigError(path, f"expected a boolean, got {_fmt(value)}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(path, f"expected an integer, got {_fmt(value)}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(path, f"expected a number, got {_fmt(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise ConfigError(path, f"expected a string, got {_fmt(value)}")
    raise TypeError(f"unsupported parameter type {tp!r} at {path}")


def _check_range(field: dataclasses.Field[Any], value: Any, path: str, tp: Any) -> None:
    meta = field.metadata
    minimum, maximum, choices = meta.get("minimum"), meta.get("maximum"), meta.get("choices")
    if choices is not None and value not in choices:
        options = ", ".join(_fmt(c) for c in choices)
        raise ConfigError(path, f"expected one of {options}, got {_fmt(value)}")
    check = meta.get("check")
    if check is not None:
        expected = check(value)
        if expected is not None:
            raise ConfigError(path, f"expected {expected}, got {_fmt(value)}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        kind = "an integer" if tp is int else "a number"
        if minimum is not None and value < minimum:
            bound = f" <= {maximum:g}" if maximum is not None else ""
            raise ConfigError(path, f"expected {kind} >= {minimum:g}{bound}, got {_fmt(value)}")
        if maximum is not None and value > maximum:
            raise ConfigError(path, f"expected {kind} <= {maximum:g}, got {_fmt(value)}")


def did_you_mean(word: str, options: Iterable[str]) -> str:
    """A ' (did you mean "x"?)' suffix, or nothing when no option is close."""
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return f' (did you mean "{close[0]}"?)' if close else ""


def field_names(cls: type) -> set[str]:
    """Every key a parameter class accepts, aliases included."""
    names: set[str] = set()
    for f in dataclasses.fields(cls):
        names.add(f.name)
        names.update(f.metadata.get("aliases", ()))
    return names


def parse_params(cls: type[T], mapping: Any, path: str, *, ignore: Iterable[str] = ()) -> T:
    """Build ``cls`` from a YAML mapping; unknown keys (not in ``ignore``) are errors."""
    if not isinstance(mapping, Mapping):
        raise ConfigError(path, f"expected a mapping, got {_fmt(mapping)}")
    hints = typing.get_type_hints(cls)
    known = field_names(cls)
    ignored = set(ignore)
    for key in mapping:
        if key not in known and key not in ignored:
            raise ConfigError(_join(path, str(key)), "unknown parameter" + did_you_mean(str(key), known))
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        key_path = _join(path, f.name)
        present = [k for k in (f.name, *f.metadata.get("aliases", ())) if k in mapping]
        if not present:
            if f.default is _MISSING and f.default_factory is _MISSING:
                raise ConfigError(key_path, f"required parameter missing (expected {_type_name(hints[f.name])})")
            continue
        tp = hints[f.name]
        value = _coerce(tp, mapping[present[0]], key_path)
        _check_range(f, value, key_path, tp)
        values[f.name] = value
    try:
        return cls(**values)
    except ConfigError as exc:  # cross-field checks in __post_init__ name keys relative to the section
        raise ConfigError(_join(path, exc.path), exc.message) from exc


def no_effect_notes(cls: type, mapping: Any, path: str) -> list[str]:
    """One warning per key of ``mapping`` (nested sections too) that ``cls`` accepts with no effect.

    Pure, like :func:`parse_params`, which has accepted ``mapping`` already: a server's configure
    logs these with its other configuration warnings, so each is said once per configure.
    """
    if not isinstance(mapping, Mapping):
        return []
    hints = typing.get_type_hints(cls)
    notes: list[str] = []
    for f in dataclasses.fields(cls):
        for key in (f.name, *f.metadata.get("aliases", ())):
            if key not in mapping:
                continue
            if f.metadata.get("no_effect"):
                notes.append(
                    f"{_join(path, key)}: accepted for the original's files, has no effect because "
                    f"{f.metadata['no_effect']}"
                )
                continue
            nested = hints[f.name] if dataclasses.is_dataclass(hints[f.name]) else f.metadata.get("section")
            if nested is not None:
                notes.extend(no_effect_notes(nested, mapping[key], _join(path, key)))
    return notes


def describe_params(cls: type) -> list[ParamInfo]:
    """Flattened description of a parameter class (nested classes use dotted names)."""
    hints = typing.get_type_hints(cls)
    out: list[ParamInfo] = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp) and isinstance(tp, type):
            for inner in describe_params(tp):
                out.append(dataclasses.replace(inner, name=f"{f.name}.{inner.name}"))
            continue
        required = f.default is _MISSING and f.default_factory is _MISSING
        if f.default_factory is not _MISSING:
            default = f.default_factory()  # type: ignore[operator]
        else:
            default = None if required else f.default
        out.append(
            ParamInfo(
                name=f.name,
                type_name=_type_name(tp),
                default=default,
                required=required,
                doc=str(f.metadata.get("doc", "")),
                secret=bool(f.metadata.get("secret", False)),
            )
        )
    return out


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key
