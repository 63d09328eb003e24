"""The contract every installed plugin keeps, whatever its kind and whoever wrote it.

The plugins are those `dc list-plugins` lists (the entry points of dc.measurements,
dc.conditions and dc.destinations); for each one:

- it loads, subclasses its kind's base and has a one-line description;
- its page is README.md in its own folder, documents every parameter with type and default, and
  is linked from docs/plugins/<kind>/index.md;
- the page's YAML examples are valid configurations (as `dc validate` checks them) and at least
  one of them configures this plugin;
- a measurement's schema is a valid draft-07 schema (or it says it has none), and the page's JSON
  output examples match it;
- configure → activate → deactivate → cleanup works with the values of the page's example.

Nothing here names a plugin: a new one is covered by adding its folder and entry point.
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml
from rclpy.node import Node

from dc_bringup.validate import validate_params_file
from dc_core import plugins
from dc_core.errors import PluginError
from dc_core.measurement import BasePaths, Measurement
from dc_core.params import describe_params
from dc_core.plugin import Plugin
from dc_core.testing import FakeContext
from tests.bringup_util import REPO, dc

SERVER_OF_KIND = {
    "measurements": "measurement_server",
    "conditions": "measurement_server",
    "destinations": "destination_server",
}


@dataclass(frozen=True)
class Installed:
    kind: str
    name: str
    cls: type[Plugin[Any]]

    @property
    def page(self) -> Path:
        return Path(sys.modules[self.cls.__module__].__file__ or "").parent / "README.md"

    def __str__(self) -> str:
        return self.name


def installed() -> list[Installed]:
    found = []
    for kind in plugins.GROUPS:
        for info in plugins.list_plugins(kind):
            found.append(Installed(kind, info.name, plugins.load_plugin(kind, info.name)))
    return found


INSTALLED = installed()


def yaml_blocks(text: str) -> list[str]:
    return re.findall(r"```yaml\n(.*?)```", text, flags=re.DOTALL)


def names_of(plugin: Installed) -> set[str]:
    """Its entry-point name and the aliases registered for the same class."""
    return {p.name for p in INSTALLED if p.kind == plugin.kind and p.cls is plugin.cls}


def parameter_row(text: str, name: str) -> list[str] | None:
    """The cells of the table row documenting parameter ``name``, if the page has one."""
    for line in text.splitlines():
        if line.startswith(f"| `{name}` |"):
            return [cell.strip() for cell in line.strip().strip("|").split("|")]
    return None


def documented_default(cell: str) -> Any:
    """The default a page shows, read as YAML: as a user would write the value."""
    return yaml.safe_load(cell.strip("`"))


def test_every_kind_has_plugins_and_dc_list_plugins_shows_the_same_set() -> None:
    assert {p.kind for p in INSTALLED} == set(plugins.GROUPS)
    listed = dc("list-plugins").stdout
    assert sorted(re.findall(r"^  (\S+)", listed, flags=re.M)) == sorted(p.name for p in INSTALLED)


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_the_plugin_subclasses_its_base_and_describes_itself_in_one_line(plugin: Installed) -> None:
    assert issubclass(plugin.cls, plugins.plugin_base(plugin.kind))
    description = plugins.describe(plugin.cls)
    assert description, f"{plugin.name}: its class docstring is its description, and it has none"
    assert "\n" not in description and len(description) <= 120, description


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_its_page_documents_every_parameter_with_type_and_default(plugin: Installed) -> None:
    assert plugin.page.is_file(), f"{plugin.name}: no page at {plugin.page}"
    text = plugin.page.read_text()
    assert f"`{plugin.name}`" in text, f"{plugin.page} does not name {plugin.name}"
    for info in describe_params(plugin.cls.Params):
        row = parameter_row(text, info.name)
        assert row is not None, f"{plugin.page} lacks a row for parameter {info.name}"
        assert len(row) >= 4 and row[1], f"{plugin.page}: {info.name} row has no type: {row}"
        if info.required:
            assert "required" in row[2], f"{plugin.page}: {info.name} is required, the page says {row[2]}"
        else:
            assert documented_default(row[2]) == info.default, (
                f"{plugin.page}: {info.name} defaults to {info.default!r}, the page says {row[2]}"
            )


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_its_page_is_linked_from_the_index_of_its_kind(plugin: Installed) -> None:
    index = REPO / "docs" / "plugins" / plugin.kind / "index.md"
    link = Path("../../..") / plugin.page.relative_to(REPO)
    assert f"]({link})" in index.read_text(), f"{index} has no link to {link}"


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_its_page_examples_are_valid_and_configure_it(plugin: Installed, tmp_path: Path) -> None:
    blocks = yaml_blocks(plugin.page.read_text())
    assert blocks, f"{plugin.page} has no example configuration"
    configures_it = False
    for index, block in enumerate(blocks):
        params = tmp_path / f"example_{index}.yaml"
        params.write_text(block)
        report = validate_params_file(params)  # raises ConfigError with the YAML path
        for server, config in report.configs.items():
            assert not config.warnings, f"{plugin.page} example {index}: {server} warns {config.warnings}"
        configures_it = configures_it or any(f'plugin: "{name}"' in block for name in names_of(plugin))
    assert configures_it, f"no example of {plugin.page} configures {plugin.name}"


BUILT_IN = [
    p for p in INSTALLED if p.cls.__module__.split(".")[0] in {"dc_measurements", "dc_conditions", "dc_destinations"}
]
PAGE_SECTIONS = {
    "measurements": (
        "## Parameters",
        "## Example configuration",
        "## Example output",
        "## Differences from the original",
    ),
    # A family of conditions (numeric, lists) shares one page, with an example per condition.
    "conditions": ("## Parameters", "## Differences from the original"),
    "destinations": (
        "## Parameters",
        "## Example configuration",
        "## Example output",
        "## Differences from the original",
    ),
}


@pytest.mark.parametrize("plugin", BUILT_IN, ids=str)
def test_a_built_in_page_has_the_sections_of_every_page(plugin: Installed) -> None:
    text = plugin.page.read_text()
    missing = [heading for heading in PAGE_SECTIONS[plugin.kind] if heading not in text]
    assert not missing, f"{plugin.page} lacks {missing}"


CONDITIONS = [p for p in INSTALLED if p.kind == "conditions"]


@pytest.mark.parametrize("plugin", CONDITIONS, ids=str)
def test_a_condition_leaves_topic_to_the_server(plugin: Installed) -> None:
    # `topic` is the common parameter that makes a condition judge another topic's records.
    assert "topic" not in {info.name for info in describe_params(plugin.cls.Params)}


MEASUREMENTS = [p for p in INSTALLED if p.kind == "measurements"]


@pytest.mark.parametrize("plugin", MEASUREMENTS, ids=str)
def test_a_measurement_schema_is_valid_and_the_page_outputs_match_it(plugin: Installed) -> None:
    cls = plugin.cls
    assert issubclass(cls, Measurement)
    schema = cls.load_schema()
    if cls.schema_file is None:
        assert schema is None
        return
    assert schema is not None, f"{plugin.name}: no {cls.schema_file} beside its module"
    jsonschema.Draft7Validator.check_schema(schema)
    assert set(schema.get("required", [])) <= set(schema.get("properties", {})), "a required field has no definition"
    outputs = re.findall(r"```json\n(.*?)```", plugin.page.read_text(), flags=re.DOTALL)
    assert outputs, f"{plugin.page} shows no output"
    # A schema may say that records fail it on purpose (the failed-validation demo's): then they must.
    fails_on_purpose = str(schema.get("$comment", "")).startswith("fails validation on purpose")
    for block in outputs:
        record = json.loads(block)
        # The page shows what a destination receives: the plugin's fields and DC's metadata.
        fields = {k: v for k, v in record.items() if k in schema.get("properties", {})}
        if fails_on_purpose:
            assert not jsonschema.Draft7Validator(schema).is_valid(fields), f"{plugin.page}: {block} is valid"
        else:
            jsonschema.validate(fields, schema)


def example_params(plugin: Installed, tmp_path: Path) -> Any:
    """The plugin's parameters as its page's first example sets them, parsed as the server does."""
    for index, block in enumerate(yaml_blocks(plugin.page.read_text())):
        if not any(f'plugin: "{name}"' in block for name in names_of(plugin)):
            continue
        params = tmp_path / f"example_{index}.yaml"
        params.write_text(block)
        config = validate_params_file(params).configs[SERVER_OF_KIND[plugin.kind]]
        if plugin.kind == "measurements":
            sections = list(config.measurements)
        elif plugin.kind == "conditions":
            sections = list(config.conditions.values())
        else:
            sections = list(config.destinations)
        for section in sections:
            if section.plugin_class is plugin.cls:
                return section.plugin_params
    raise AssertionError(f"no example of {plugin.page} configures {plugin.name}")


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_a_lifecycle_round_trip_works_with_the_page_example(
    plugin: Installed, ros_node: Node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))  # examples write under $HOME
    # Plugins that save files (Map, Camera, IpCamera) keep them under the test's folder.
    context = FakeContext(
        name=f"contract_{plugin.cls.__name__.lower()}",
        node=ros_node,
        paths=BasePaths(save_local_base_path=str(tmp_path / "data")),
    )
    instance = plugin.cls(context, example_params(plugin, tmp_path))
    for step in (instance.on_configure, instance.on_activate, instance.on_deactivate, instance.on_cleanup):
        step()
    assert isinstance(instance.counters(), dict)
    context.stop_worker()


class NotAMeasurement:
    """Looks like a plugin, subclasses nothing of DC's."""

    def collect(self) -> dict[str, Any]:
        return {}


def test_load_plugin_refuses_a_class_that_does_not_subclass_its_base(monkeypatch: pytest.MonkeyPatch) -> None:
    original = plugins._entry_points
    entry = EntryPoint("thirdparty/Fake", f"{__name__}:NotAMeasurement", "dc.measurements")
    monkeypatch.setattr(
        plugins,
        "_entry_points",
        lambda kind: {**original(kind), entry.name: entry} if kind == "measurements" else original(kind),
    )
    with pytest.raises(
        PluginError, match=r"not a measurement plugin: its class must subclass dc_core\.measurement\.Measurement"
    ):
        plugins.load_plugin("measurements", "thirdparty/Fake")
