"""The contract every plugin keeps, whatever its kind and whoever wrote it: `dc check-plugin NAME`.

For one installed plugin (an entry point of dc.measurements, dc.conditions or dc.destinations):

- it loads, subclasses its kind's base and has a one-line description;
- its page is README.md in its own folder, names it, and documents every parameter with type and default;
- the page's YAML examples are valid configurations (as `dc validate` checks them) and at least
  one of them configures this plugin;
- a measurement's schema is a valid draft-07 schema (or it says it has none), and the page's JSON
  output examples match it; a condition leaves ``topic`` to the server;
- configure → activate → deactivate → cleanup works with the values of the page's example.

Each check raises :class:`ContractBroken` with what is wrong and where; DC's own test suite runs the
same checks on DC's own plugins (tests/test_plugin_contract.py), a plugin author runs them with
`dc check-plugin`. Nothing here names a plugin.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import sys
import tempfile
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dc_core import plugins
from dc_core.errors import DcError
from dc_core.params import describe_params

SERVER_OF_KIND = {
    "measurements": "measurement_server",
    "conditions": "measurement_server",
    "destinations": "destination_server",
}


class ContractBroken(AssertionError):
    """One rule of the contract the plugin does not keep; the message says which and where."""


@dataclass(frozen=True)
class InstalledPlugin:
    kind: str
    name: str
    target: str  # the entry point's value, module:Class
    distribution: str

    @property
    def cls(self) -> type:
        return plugins.load_plugin(self.kind, self.name)

    @property
    def page(self) -> Path:
        return Path(sys.modules[self.cls.__module__].__file__ or "").parent / "README.md"

    def __str__(self) -> str:
        return self.name


def installed_plugins(distributions: Collection[str] | None = None) -> list[InstalledPlugin]:
    """Every installed plugin, or those of the named distributions only."""
    return [
        InstalledPlugin(info.kind, info.name, info.target, info.distribution)
        for kind in plugins.GROUPS
        for info in plugins.list_plugins(kind)
        if distributions is None or info.distribution in distributions
    ]


def find_plugin(name: str) -> list[InstalledPlugin]:
    """The plugins registered as ``name`` (one per kind that has it)."""
    return [p for p in installed_plugins() if p.name == name]


def names_of(plugin: InstalledPlugin) -> set[str]:
    """Its entry-point name and the aliases registered for the same class."""
    return {info.name for info in plugins.list_plugins(plugin.kind) if info.target == plugin.target}


def yaml_blocks(text: str) -> list[str]:
    return re.findall(r"```yaml\n(.*?)```", text, flags=re.DOTALL)


def parameter_row(text: str, name: str) -> list[str] | None:
    """The cells of the table row documenting parameter ``name``, if the page has one."""
    for line in text.splitlines():
        if line.startswith(f"| `{name}` |"):
            return [cell.strip() for cell in line.strip().strip("|").split("|")]
    return None


def documented_default(cell: str) -> Any:
    """The default a page shows, read as YAML: as a user would write the value."""
    import yaml

    return yaml.safe_load(cell.strip("`"))


def _require(condition: object, message: str) -> None:
    if not condition:
        raise ContractBroken(message)


def _page_text(plugin: InstalledPlugin) -> str:
    _require(plugin.page.is_file(), f"no page at {plugin.page} (README.md beside the plugin's module)")
    return plugin.page.read_text()


def check_loads(plugin: InstalledPlugin) -> None:
    try:
        cls = plugin.cls
    except DcError as exc:
        raise ContractBroken(str(exc)) from exc
    _require(issubclass(cls, plugins.plugin_base(plugin.kind)), f"{plugin.target} does not subclass its kind's base")


def check_description(plugin: InstalledPlugin) -> None:
    description = plugins.describe(plugin.cls)
    _require(description, f"{plugin.target}: its class docstring is its description, and it has none")
    _require(
        "\n" not in description and len(description) <= 120,
        f"{plugin.target}: the first line of its docstring is longer than 120 characters: {description}",
    )


def check_page_parameters(plugin: InstalledPlugin) -> None:
    text = _page_text(plugin)
    _require(f"`{plugin.name}`" in text, f"{plugin.page} does not name {plugin.name} (as `{plugin.name}`)")
    for info in describe_params(plugin.cls.Params):  # type: ignore[attr-defined]
        row = parameter_row(text, info.name)
        _require(row is not None, f"{plugin.page} lacks a row | `{info.name}` | type | default | description |")
        assert row is not None
        _require(len(row) >= 4 and row[1], f"{plugin.page}: the {info.name} row has no type: {row}")
        if info.required:
            _require("required" in row[2], f"{plugin.page}: {info.name} is required, the page says {row[2]}")
        else:
            _require(
                documented_default(row[2]) == info.default,
                f"{plugin.page}: {info.name} defaults to {info.default!r}, the page says {row[2]}",
            )


def check_page_examples(plugin: InstalledPlugin) -> None:
    from dc_bringup.validate import validate_params_file

    blocks = yaml_blocks(_page_text(plugin))
    _require(blocks, f"{plugin.page} has no example configuration (a ```yaml block)")
    names = names_of(plugin)
    configures_it = False
    with tempfile.TemporaryDirectory(prefix="dc-check-plugin-") as folder:
        for index, block in enumerate(blocks):
            params = Path(folder) / f"example_{index}.yaml"
            params.write_text(block)
            try:
                report = validate_params_file(params)
            except DcError as exc:
                raise ContractBroken(f"{plugin.page} example {index + 1}: {exc}") from exc
            for server, config in report.configs.items():
                _require(not config.warnings, f"{plugin.page} example {index + 1}: {server} warns {config.warnings}")
            configures_it = configures_it or any(f'plugin: "{name}"' in block for name in names)
    _require(configures_it, f'no example of {plugin.page} configures it (plugin: "{plugin.name}")')


def check_condition_topic(plugin: InstalledPlugin) -> None:
    # `topic` is the common parameter that makes a condition judge another topic's records.
    _require(
        "topic" not in {info.name for info in describe_params(plugin.cls.Params)},  # type: ignore[attr-defined]
        f"{plugin.target}: a condition leaves the parameter `topic` to the server (it judges another topic's records)",
    )


def check_schema(plugin: InstalledPlugin) -> None:
    import jsonschema

    from dc_core.measurement import Measurement

    cls = plugin.cls
    assert issubclass(cls, Measurement)
    schema = cls.load_schema()
    if cls.schema_file is None:
        _require(schema is None, f"{plugin.target}: schema_file is None, yet a schema loaded")
        return
    where = Path(sys.modules[cls.__module__].__file__ or "").parent / cls.schema_file
    _require(schema is not None, f"no {where}: a measurement's schema.json sits beside its module")
    assert schema is not None
    try:
        jsonschema.Draft7Validator.check_schema(schema)
    except jsonschema.SchemaError as exc:
        raise ContractBroken(f"{where} is not a valid draft-07 schema: {exc.message}") from exc
    _require(
        set(schema.get("required", [])) <= set(schema.get("properties", {})),
        f"{where}: a required field has no definition under properties",
    )
    outputs = re.findall(r"```json\n(.*?)```", _page_text(plugin), flags=re.DOTALL)
    _require(outputs, f"{plugin.page} shows no output (a ```json block of a record)")
    # A schema may say that records fail it on purpose (the failed-validation demo's): then they must.
    fails_on_purpose = str(schema.get("$comment", "")).startswith("fails validation on purpose")
    for block in outputs:
        try:
            record = json.loads(block)
        except ValueError as exc:
            raise ContractBroken(f"{plugin.page}: an example output is not JSON: {exc}") from exc
        # The page shows what a destination receives: the plugin's fields and DC's metadata.
        fields = {k: v for k, v in record.items() if k in schema.get("properties", {})}
        valid = jsonschema.Draft7Validator(schema).is_valid(fields)
        if fails_on_purpose:
            _require(not valid, f"{plugin.page}: {block.strip()} is valid, the schema says it fails on purpose")
        else:
            _require(valid, f"{plugin.page}: the example output {block.strip()} does not match {where}")


def example_params(plugin: InstalledPlugin, folder: Path) -> Any:
    """The plugin's parameters as its page's first example that configures it sets them, parsed as the server does."""
    from dc_bringup.validate import validate_params_file

    names = names_of(plugin)
    cls = plugin.cls
    for index, block in enumerate(yaml_blocks(_page_text(plugin))):
        if not any(f'plugin: "{name}"' in block for name in names):
            continue
        params = folder / f"example_{index}.yaml"
        params.write_text(block)
        config = validate_params_file(params).configs[SERVER_OF_KIND[plugin.kind]]
        if plugin.kind == "measurements":
            sections = list(config.measurements)
        elif plugin.kind == "conditions":
            sections = list(config.conditions.values())
        else:
            sections = list(config.destinations)
        for section in sections:
            if section.plugin_class is cls:
                return section.plugin_params
    raise ContractBroken(f"no example of {plugin.page} configures {plugin.name}")


@contextlib.contextmanager
def _home(folder: Path) -> Iterator[None]:
    """$HOME in ``folder``: examples write under it (~/…), and a check leaves the user's alone."""
    saved = os.environ.get("HOME")
    os.environ["HOME"] = str(folder)
    try:
        yield
    finally:
        if saved is None:
            del os.environ["HOME"]
        else:
            os.environ["HOME"] = saved


def check_lifecycle(plugin: InstalledPlugin, node: Any = None) -> None:
    from dc_core.measurement import BasePaths
    from dc_core.testing import FakeContext

    with tempfile.TemporaryDirectory(prefix="dc-check-plugin-") as tmp, _home(Path(tmp)):
        folder = Path(tmp)
        context = FakeContext(
            name=f"contract_{plugin.cls.__name__.lower()}",
            node=node,
            paths=BasePaths(save_local_base_path=str(folder / "data")),
        )
        instance = plugin.cls(context, example_params(plugin, folder))
        step = "the constructor"
        try:
            for step in ("on_configure", "on_activate", "on_deactivate", "on_cleanup"):
                getattr(instance, step)()
            step = "counters"
            _require(isinstance(instance.counters(), dict), f"{plugin.target}.counters() must return a dict")
        except ContractBroken:
            raise
        except Exception as exc:
            raise ContractBroken(f"{step} with the page's example failed: {type(exc).__name__}: {exc}") from exc
        finally:
            context.stop_worker()


Check = Callable[[InstalledPlugin], None]


def checks_of(plugin: InstalledPlugin, node: Any = None) -> list[tuple[str, Check]]:
    """The contract's checks that apply to ``plugin``'s kind, by name, in order."""
    found: list[tuple[str, Check]] = [
        ("loads", check_loads),
        ("description", check_description),
        ("page parameters", check_page_parameters),
        ("page examples", check_page_examples),
    ]
    if plugin.kind == "measurements":
        found.append(("schema", check_schema))
    if plugin.kind == "conditions":
        found.append(("topic left to the server", check_condition_topic))
    found.append(("lifecycle", lambda p: check_lifecycle(p, node)))
    return found


@dataclass(frozen=True)
class Finding:
    plugin: str
    check: str
    problem: str  # empty: kept

    @property
    def ok(self) -> bool:
        return not self.problem


def run_contract(plugin: InstalledPlugin, node: Any = None) -> list[Finding]:
    """Every check on ``plugin``; after a plugin that does not load, nothing else can be checked."""
    findings = []
    for name, check in checks_of(plugin, node):
        try:
            check(plugin)
            problem = ""
        except ContractBroken as exc:
            problem = str(exc) or "failed"
        except Exception as exc:  # a check must report a plugin's defect, never crash on it
            problem = f"{type(exc).__name__}: {exc}"
        findings.append(Finding(plugin.name, name, problem))
        if problem and name == "loads":
            break
    return findings


def _ros_node() -> tuple[Any, Callable[[], None]]:
    """A node of a context of its own for plugins that subscribe or make timers; (None, no-op) without ROS."""
    try:
        import rclpy
        from rclpy.context import Context

        context = Context()
        rclpy.init(context=context)
        node = rclpy.create_node(f"dc_check_plugin_{os.getpid()}", context=context)
    except Exception:  # the round trip then says which plugin needs a node
        return None, lambda: None

    def close() -> None:
        node.destroy_node()
        context.try_shutdown()

    return node, close


def main(names: Collection[str]) -> int:
    """`dc check-plugin NAME...`: 0 when every named plugin keeps the contract, 1 when one does not, 2 unknown."""
    from dc_core.params import did_you_mean

    chosen: list[InstalledPlugin] = []
    for name in names:
        found = find_plugin(name)
        if not found:
            known = {p.name for p in installed_plugins()}
            print(f"dc check-plugin: no installed plugin {name!r}{did_you_mean(name, known)}", file=sys.stderr)
            print(
                "  (`dc list-plugins` lists them; pip install your package into DC's environment first)",
                file=sys.stderr,
            )
            return 2
        chosen.extend(found)
    node, close = _ros_node()
    failed = 0
    try:
        for plugin in chosen:
            print(f"{plugin.name} ({plugin.kind[:-1]}, {plugin.target}, distribution {plugin.distribution}):")
            findings = run_contract(plugin, node)
            for finding in findings:
                said = finding.check if finding.ok else f"{finding.check}: {finding.problem}"
                print(f"  {'ok' if finding.ok else 'FAILED':<7} {said}")
            broken = [f for f in findings if not f.ok]
            failed += bool(broken)
            print(
                f"  {'keeps' if not broken else 'breaks'} DC's plugin contract"
                + (f" ({len(broken)} of {len(findings)} checks failed)" if broken else "")
            )
    finally:
        close()
    return 1 if failed else 0
