"""`dc new-plugin KIND PACKAGE/Class`: a plugin package that installs, loads and keeps DC's plugin contract.

The package is ``<dir>/<package-with-dashes>/``; a second plugin named in the same package is added
to it (its folder and one entry-point line), so one package can hold several plugins of any kinds.
What is written is a working plugin (a counter, a threshold, a JSON-lines file) to be replaced by
the real thing: `dc check-plugin PACKAGE/Class` passes on it as it is.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

KINDS = {"measurement": "measurements", "condition": "conditions", "destination": "destinations"}
GROUP = {"measurements": "dc.measurements", "conditions": "dc.conditions", "destinations": "dc.destinations"}
NAME = re.compile(r"(?P<package>[a-z][a-z0-9_]*)/(?P<cls>[A-Z][A-Za-z0-9]*)")


class ScaffoldError(ValueError):
    pass


def snake(name: str) -> str:
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name).lower()


PYPROJECT = """\
[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "{dist}"
version = "0.1.0"
description = "DC plugins of {package}"
requires-python = ">=3.11"
# DC itself (distribution ros2-dc) is not on PyPI: install this package into DC's environment, after DC.
dependencies = []

[tool.setuptools.packages.find]
include = ["{package}*"]

[tool.setuptools.package-data]
# Each plugin folder ships its page and (measurements) its schema with the code.
{package} = ["py.typed", "*/schema.json", "*/README.md"]

# The entry-point name is the plugin type written in YAML (plugin: "{package}/Name").
"""

PACKAGE_README = """\
# {dist}

DC plugins, made with `dc new-plugin`. Install into DC's environment and check each plugin:

```console
$ pip install -e .                 # with DC's venv active (make install made it)
$ dc list-plugins                  # lists them, with [{dist}]
$ dc check-plugin {package}/Name   # DC's plugin contract, as DC's own plugins keep it
$ python -m pytest {package}       # the plugins' own tests
```

One folder per plugin: the module (its parameter class and plugin class), `schema.json`
(measurements), its page `README.md`, its test. See DC's docs/plugin_development.md.
"""

MEASUREMENT = '''\
"""{cls}: a counter of its own collections, to be replaced by what you measure."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dc_core.measurement import Measurement
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class {cls}Params:
    start: int = param(0, minimum=0, doc="The first count")


class {cls}(Measurement[{cls}Params]):
    """Counts its collections (replace collect() with what you measure)."""

    def __init__(self, context: Any, params: {cls}Params) -> None:
        super().__init__(context, params)
        self.count = params.start

    def collect(self) -> dict[str, Any] | None:
        # Runs on the server's main thread: a collection that waits sets collect_in_worker = True.
        sample = {{"count": self.count}}
        self.count += 1
        return sample
'''

SCHEMA = """\
{
  "$schema": "http://json-schema.org/draft-07/schema#",
  "type": "object",
  "properties": {
    "count": {"type": "integer", "minimum": 0}
  },
  "required": ["count"],
  "additionalProperties": false
}
"""

# The destination of the pages' examples: the records of one measurement on stdout.
STDOUT_OF = """\
destination_server:
  ros__parameters:
    destination_plugins: ["stdout"]
    stdout:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/{measurement}"]
"""

MEASUREMENT_PAGE = (
    """\
# {cls} (`{name}`)

Counts its own collections: the first record holds `start`, each next one one more. Replace this
page's text, parameters and examples with your measurement's.

## Parameters

| Parameter | Type | Default | Description |
|---|---|---|---|
| `start` | integer | `0` | The first count |

Plus DC's common measurement parameters (`plugin`, `polling_interval`, `tags`, conditions…).

## Example configuration

```yaml
measurement_server:
  ros__parameters:
    measurement_plugins: ["{folder}"]
    {folder}:
      plugin: "{name}"
      start: 1
      polling_interval: 1000
      tags: ["stdout"]
"""
    + STDOUT_OF.format(measurement="{folder}")
    + """```

## Example output

```json
{{"count": 1, "name": "{folder}", "run_id": "3", "tags": ["stdout"]}}
```

Schema ([`schema.json`](schema.json)): `count`, an integer from 0, required.
"""
)

MEASUREMENT_TEST = '''\
"""{cls}: what a destination receives from it."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
from dc_core.testing import PluginHarness

from {package}.{folder} import {cls}


def test_it_counts_from_start_and_its_records_match_its_schema() -> None:
    harness = PluginHarness()
    measurement = harness.start({cls}, {{"start": 5}})
    samples = [measurement.collect(), measurement.collect()]
    assert samples == [{{"count": 5}}, {{"count": 6}}]
    schema = json.loads((Path(__file__).parent / "schema.json").read_text())
    for sample in samples:
        jsonschema.validate(sample, schema)
    harness.stop(measurement)
'''

CONDITION = '''\
"""{cls}: a number in the sample above a threshold, to be replaced by your own judgement."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dc_core.condition import Condition
from dc_core.jsonpath import get_path
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class {cls}Params:
    key: str = param(doc="Key path of the number, `/`-separated")
    threshold: float = param(0.0, doc="Active when the number is above this")


class {cls}(Condition[{cls}Params]):
    """Number at the key path above `threshold` (replace evaluate() with your own judgement)."""

    # A measurement whose schema types `key` otherwise is refused at configure time.
    value_types = frozenset({{"number", "integer"}})

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        # A missing key raises PathNotFound (a LookupError): the server takes that as inactive.
        value = get_path(sample, self.params.key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TypeError(f"not a number: {{value!r}}")
        return value > self.params.threshold
'''

CONDITION_PAGE = (
    """\
# {cls} (`{name}`)

Active when the number at `key` is above `threshold`. A missing key or a value that is not a
number leaves it inactive. Replace this page's text, parameters and examples with your condition's.

## Parameters

| Parameter | Type | Default | Description |
|---|---|---|---|
| `key` | string | (required) | Key path of the number, `/`-separated |
| `threshold` | number | `0.0` | Active when the number is above this |

Plus DC's common condition parameters `plugin` and `topic`.

## Example configuration

Publish a measurement only while its `load` is above 0.5:

```yaml
measurement_server:
  ros__parameters:
    measurement_plugins: ["busy_load"]
    condition_plugins: ["{folder}"]
    {folder}:
      plugin: "{name}"
      key: "load"
      threshold: 0.5
    busy_load:
      plugin: "dc_measurements/Dummy"
      record: '{{"load": 0.75}}'
      polling_interval: 1000
      if_all_conditions: ["{folder}"]
      tags: ["stdout"]
"""
    + STDOUT_OF.format(measurement="busy_load")
    + """```
"""
)

CONDITION_TEST = '''\
"""{cls}: active above the threshold, inactive otherwise."""

from __future__ import annotations

import pytest
from dc_core.testing import PluginHarness

from {package}.{folder} import {cls}


def test_it_is_active_above_the_threshold_only() -> None:
    harness = PluginHarness()
    condition = harness.start({cls}, {{"key": "load", "threshold": 0.5}})
    assert condition.evaluate({{"load": 0.75}})
    assert not condition.evaluate({{"load": 0.25}})
    with pytest.raises(LookupError):
        condition.evaluate({{"other": 1}})
    harness.stop(condition)
'''

DESTINATION = '''\
"""{cls}: each record appended to a file as a JSON line, to be replaced by your store's client."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, RetryableError, SendOutcome
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class {cls}Params:
    path: str = param("~/{folder}.jsonl", doc="File the records are appended to, one JSON object a line")


class {cls}(Destination[{cls}Params]):
    """Appends each record to a file as a JSON line (replace send() with your store's client)."""

    def __init__(self, context: Any, params: {cls}Params) -> None:
        super().__init__(context, params)
        self.file = Path(params.path).expanduser()

    def on_configure(self) -> None:
        self.file.parent.mkdir(parents=True, exist_ok=True)

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        # Runs on the destination's sender thread; DC buffers, retries with backoff and counts.
        try:
            with self.file.open("a") as out:
                out.writelines(record.to_json() + "\\n" for record in batch)
        except OSError as exc:
            raise RetryableError(f"cannot write {{self.file}}: {{exc}}") from exc
        return None
'''

DESTINATION_PAGE = """\
# {cls} (`{name}`)

Appends each record to a file, one JSON object a line. Replace this page's text, parameters and
examples with your destination's.

## Parameters

| Parameter | Type | Default | Description |
|---|---|---|---|
| `path` | string | `~/{folder}.jsonl` | File the records are appended to, one JSON object a line |

Plus DC's common destination parameters (`plugin`, `inputs` — required —, `debug`, `time_format`, `time_key`).

## Example configuration

```yaml
measurement_server:
  ros__parameters:
    measurement_plugins: ["uptime"]
    uptime:
      plugin: "dc_measurements/Uptime"
      polling_interval: 1000
      tags: ["{folder}"]
destination_server:
  ros__parameters:
    destination_plugins: ["{folder}"]
    {folder}:
      plugin: "{name}"
      inputs: ["/dc/measurement/uptime"]
      path: "~/dc_records.jsonl"
```

## Example output

A line of `~/dc_records.jsonl`:

```json
{{"time": 1234, "name": "uptime", "run_id": "3", "tags": ["{folder}"]}}
```
"""

DESTINATION_TEST = '''\
"""{cls}: every record of a batch lands in the file."""

from __future__ import annotations

import json
from pathlib import Path

from dc_core.destination import OutgoingRecord
from dc_core.testing import PluginHarness

from {package}.{folder} import {cls}


def test_each_record_is_a_line_of_the_file(tmp_path: Path) -> None:
    harness = PluginHarness()
    out = tmp_path / "records.jsonl"
    destination = harness.start({cls}, {{"path": str(out)}})
    batch = [OutgoingRecord(f"id-{{n}}", "/dc/measurement/x", n, {{"n": n}}) for n in range(3)]
    assert destination.send(batch) is None
    assert [json.loads(line) for line in out.read_text().splitlines()] == [{{"n": n}} for n in range(3)]
    harness.stop(destination)
'''

FILES = {
    "measurements": {"__init__.py": MEASUREMENT, "schema.json": SCHEMA, "README.md": MEASUREMENT_PAGE},
    "conditions": {"__init__.py": CONDITION, "README.md": CONDITION_PAGE},
    "destinations": {"__init__.py": DESTINATION, "README.md": DESTINATION_PAGE},
}
TESTS = {"measurements": MEASUREMENT_TEST, "conditions": CONDITION_TEST, "destinations": DESTINATION_TEST}


def add_entry_point(pyproject: str, group: str, name: str, target: str) -> str:
    """``pyproject`` with ``"name" = "target"`` in the entry-point table of ``group`` (made when missing)."""
    header = f'[project.entry-points."{group}"]'
    line = f'"{name}" = "{target}"'
    if header not in pyproject:
        return pyproject.rstrip("\n") + f"\n\n{header}\n{line}\n"
    start = pyproject.index(header) + len(header)
    return pyproject[:start] + f"\n{line}" + pyproject[start:]


def scaffold(kind: str, name: str, directory: Path) -> list[Path]:
    """Write plugin ``name`` (PACKAGE/Class) of ``kind`` (measurement, condition, destination) into its
    package under ``directory``; the files written, in order."""
    group_kind = KINDS[kind]
    match = NAME.fullmatch(name)
    if match is None:
        raise ScaffoldError(
            f"{name!r}: a plugin is named PACKAGE/Class, the package in lower case, the class in CamelCase "
            "(my_robot_dc/Battery)"
        )
    package, cls = match["package"], match["cls"]
    folder = snake(cls)
    dist = package.replace("_", "-")
    root = directory / dist
    values = {"package": package, "cls": cls, "folder": folder, "name": name, "dist": dist}
    plugin_dir = root / package / folder
    if plugin_dir.exists():
        raise ScaffoldError(f"{plugin_dir} exists already: choose another class name")
    written: list[Path] = []

    def write(path: Path, text: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        written.append(path)

    pyproject = root / "pyproject.toml"
    if not pyproject.exists():
        write(pyproject, PYPROJECT.format(**values))
        write(root / "README.md", PACKAGE_README.format(**values))
        write(root / package / "__init__.py", f'"""DC plugins of {package}."""\n')
        write(root / package / "py.typed", "")
    text = pyproject.read_text()
    if f'"{name}" =' in text:
        raise ScaffoldError(f"{pyproject} registers {name} already")
    for file, template in FILES[group_kind].items():
        write(plugin_dir / file, template if file == "schema.json" else template.format(**values))
    write(plugin_dir / f"test_{folder}.py", TESTS[group_kind].format(**values))
    pyproject.write_text(add_entry_point(text, GROUP[group_kind], name, f"{package}.{folder}:{cls}"))
    if pyproject not in written:
        written.append(pyproject)
    return written


def main(kind: str, name: str, directory: str) -> int:
    try:
        written = scaffold(kind, name, Path(directory))
    except ScaffoldError as exc:
        print(f"dc new-plugin: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    root = next(path for path in written if path.name == "pyproject.toml").parent
    print(f"next: pip install -e {root}  (into DC's environment), then: dc check-plugin {name}")
    return 0
