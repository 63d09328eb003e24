"""DC's own plugins keep the contract `dc check-plugin` holds any plugin to (dc_bringup/plugin_contract.py),
and what DC asks of its own pages besides: a link from docs/plugins/<kind>/index.md, the sections of
every page.

DC's own plugins are the entry points of the distributions whose pyproject.toml is in this repository
(DC itself and the example package in examples/): a plugin package installed beside DC is not DC's
to test, so installing one leaves this suite as it was. Nothing here names a plugin: a new one is
covered by adding its folder and entry point.
"""

from __future__ import annotations

import importlib
import re
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import pytest
from rclpy.node import Node

from dc_bringup import plugin_contract as contract
from dc_bringup.plugin_contract import InstalledPlugin
from dc_core import plugins
from dc_core.errors import PluginError
from tests.bringup_util import REPO, dc

# Each of DC's own distributions, by name: the folder of its pyproject.toml.
OWN_DISTRIBUTIONS = {
    tomllib.loads(pyproject.read_text())["project"]["name"]: pyproject.parent
    for pyproject in [REPO / "pyproject.toml", *sorted((REPO / "examples").glob("*/pyproject.toml"))]
}
INSTALLED = contract.installed_plugins(OWN_DISTRIBUTIONS)


def source_page(plugin: InstalledPlugin) -> Path:
    """The plugin's page in this checkout, wherever its distribution was installed from (an editable
    install of the example package may point at another checkout)."""
    module = plugin.target.partition(":")[0]
    top = module.partition(".")[0]
    installed = plugin.page
    package_root = Path(importlib.import_module(top).__file__ or "").parent.parent
    return OWN_DISTRIBUTIONS[plugin.distribution] / installed.relative_to(package_root)


def test_every_kind_has_plugins_and_dc_list_plugins_shows_them() -> None:
    assert {p.kind for p in INSTALLED} == set(plugins.GROUPS)
    listed = dc("list-plugins").stdout
    assert {p.name for p in INSTALLED} <= set(re.findall(r"^  (\S+)", listed, flags=re.M))


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_the_plugin_subclasses_its_base_and_describes_itself_in_one_line(plugin: InstalledPlugin) -> None:
    contract.check_loads(plugin)
    contract.check_description(plugin)


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_its_page_documents_every_parameter_with_type_and_default(plugin: InstalledPlugin) -> None:
    contract.check_page_parameters(plugin)


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_its_page_is_linked_from_the_index_of_its_kind(plugin: InstalledPlugin) -> None:
    index = REPO / "docs" / "plugins" / plugin.kind / "index.md"
    page = source_page(plugin)
    assert page.is_file(), f"{plugin.name}: no page at {page}"
    link = Path("../../..") / page.relative_to(REPO)
    assert f"]({link})" in index.read_text(), f"{index} has no link to {link}"


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_its_page_examples_are_valid_and_configure_it(plugin: InstalledPlugin) -> None:
    contract.check_page_examples(plugin)


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
def test_a_built_in_page_has_the_sections_of_every_page(plugin: InstalledPlugin) -> None:
    text = plugin.page.read_text()
    missing = [heading for heading in PAGE_SECTIONS[plugin.kind] if heading not in text]
    assert not missing, f"{plugin.page} lacks {missing}"


CONDITIONS = [p for p in INSTALLED if p.kind == "conditions"]


@pytest.mark.parametrize("plugin", CONDITIONS, ids=str)
def test_a_condition_leaves_topic_to_the_server(plugin: InstalledPlugin) -> None:
    contract.check_condition_topic(plugin)


MEASUREMENTS = [p for p in INSTALLED if p.kind == "measurements"]


@pytest.mark.parametrize("plugin", MEASUREMENTS, ids=str)
def test_a_measurement_schema_is_valid_and_the_page_outputs_match_it(plugin: InstalledPlugin) -> None:
    contract.check_schema(plugin)


@pytest.mark.parametrize("plugin", INSTALLED, ids=str)
def test_a_lifecycle_round_trip_works_with_the_page_example(plugin: InstalledPlugin, ros_node: Node) -> None:
    contract.check_lifecycle(plugin, ros_node)


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
