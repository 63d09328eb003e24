"""Plugin discovery through entry points (``dc.measurements``, ``dc.conditions``, ``dc.destinations``).

The entry-point name is the plugin type used in YAML (``dc_measurements/Uptime``); built-in plugins
register exactly like a third-party package does.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Generic, Protocol, TypeVar

from dc_core.errors import ConfigError, PluginError
from dc_core.params import did_you_mean, field_names, no_effect_notes, parse_params


class _NamesItsPlugin(Protocol):
    @property
    def plugin(self) -> str: ...


CommonT = TypeVar("CommonT", bound=_NamesItsPlugin)

GROUPS = {
    "measurements": "dc.measurements",
    "conditions": "dc.conditions",
    "destinations": "dc.destinations",
}


@dataclass(frozen=True)
class PluginInfo:
    kind: str
    name: str
    target: str
    distribution: str


def _entry_points(kind: str) -> dict[str, EntryPoint]:
    return {ep.name: ep for ep in entry_points(group=GROUPS[kind])}


def list_plugins(kind: str) -> list[PluginInfo]:
    out = []
    for ep in _entry_points(kind).values():
        dist = ep.dist.name if ep.dist is not None else "?"
        out.append(PluginInfo(kind=kind, name=ep.name, target=ep.value, distribution=dist))
    return sorted(out, key=lambda p: p.name)


def load_plugin(kind: str, name: str) -> type:
    """The class registered as ``name``; a clear :class:`PluginError` otherwise."""
    available = _entry_points(kind)
    ep = available.get(name)
    if ep is None:
        singular = kind[:-1]
        raise PluginError(f"unknown {singular} plugin {name!r}{did_you_mean(name, available)}")
    try:
        cls = ep.load()
    except Exception as exc:  # a broken third-party package must not take DC down with a traceback
        raise PluginError(f"plugin {name!r} ({ep.value}) failed to import: {exc}") from exc
    if not isinstance(cls, type):
        raise PluginError(f"plugin {name!r} ({ep.value}) is not a class")
    base = plugin_base(kind)
    if not issubclass(cls, base):
        raise PluginError(
            f"plugin {name!r} ({ep.value}) is not a {kind[:-1]} plugin: "
            f"its class must subclass {base.__module__}.{base.__qualname__}"
        )
    return cls


def load_plugin_class(kind: str, name: str, path: str) -> type:
    """:func:`load_plugin` for a configuration: a :class:`ConfigError` at ``<path>.plugin`` when it fails."""
    try:
        return load_plugin(kind, name)
    except PluginError as exc:
        raise ConfigError(f"{path}.plugin", str(exc)) from exc


@dataclass(frozen=True)
class PluginSection(Generic[CommonT]):
    """One plugin instance's section of a server, parsed: its common keys, its class, the classes
    that share the section (``shared``, in order), its own parameters, and one warning per key it
    accepts without effect (``notes``, for the server's configure warnings)."""

    common: CommonT
    plugin_class: type
    shared: tuple[Any, ...]
    params: Any
    notes: tuple[str, ...] = ()


def parse_plugin_section(
    kind: str,
    body: Mapping[str, Any],
    path: str,
    common_cls: type[CommonT],
    *,
    shared: Iterable[type] = (),
) -> PluginSection[CommonT]:
    """Parse a plugin instance's section: the common keys (``common_cls``, whose ``plugin`` names the
    type), the plugin's class, the parameter classes every instance of the server shares (``shared``),
    and the plugin's own ``Params``; every error names its YAML path under ``path``, and the keys they
    accept without effect are named in the result's ``notes``.

    A key none of them knows is reported once, as an unknown parameter of the plugin, with a
    suggestion taken from all of them.
    """
    common_keys = field_names(common_cls)
    common = parse_params(common_cls, body, path, ignore=set(body) - common_keys)
    plugin = common.plugin
    plugin_class = load_plugin_class(kind, plugin, path)
    params_class: type = plugin_class.Params  # type: ignore[attr-defined]
    shared_classes = tuple(shared)
    others = set(common_keys)
    for cls in shared_classes:
        others |= field_names(cls)
    # Checked over the common and the plugin's keys together: the plugin's Params alone would
    # suggest nothing for a misspelled common key (polling_intervall).
    known = others | field_names(params_class)
    for key in body:
        if key not in known:
            raise ConfigError(f"{path}.{key}", f"unknown parameter of {plugin}{did_you_mean(str(key), known)}")
    shared_params: tuple[Any, ...] = tuple(
        parse_params(cls, body, path, ignore=set(body) - field_names(cls)) for cls in shared_classes
    )
    params: Any = parse_params(params_class, body, path, ignore=others)
    notes = tuple(
        note for cls in (common_cls, *shared_classes, params_class) for note in no_effect_notes(cls, body, path)
    )
    return PluginSection(common, plugin_class, shared_params, params, notes)


def plugin_base(kind: str) -> type:
    """The class every plugin of ``kind`` subclasses."""
    from dc_core.condition import Condition
    from dc_core.destination import Destination
    from dc_core.measurement import Measurement

    bases: dict[str, type] = {"measurements": Measurement, "conditions": Condition, "destinations": Destination}
    return bases[kind]


def describe(cls: type) -> str:
    """First line of a plugin's docstring: its one-line description."""
    doc = (cls.__doc__ or "").strip()
    return doc.splitlines()[0] if doc else ""
