"""Plugin discovery through entry points (``dc.measurements``, ``dc.conditions``, ``dc.destinations``).

The entry-point name is the plugin type used in YAML (``dc_measurements/Uptime``); built-in plugins
register exactly like a third-party package does.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from dc_core.errors import PluginError
from dc_core.params import did_you_mean

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
