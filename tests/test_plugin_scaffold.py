"""`dc new-plugin` and `dc check-plugin` as a plugin author meets them (issue 30, item 7).

One package holding a plugin of each kind is scaffolded with `dc new-plugin`, installed as a
third-party package (pip, without build isolation, into a folder of its own on PYTHONPATH: DC's
environment is shared by other test runs, and removing the folder uninstalls it), and checked with
`dc check-plugin`; then the same package with its measurement's schema removed.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.bringup_util import BIN, REPO, dc

PACKAGE = "my_robot_dc"
PLUGINS = {"measurement": "my_robot_dc/BatteryLevel", "condition": "my_robot_dc/Above", "destination": "my_robot_dc/Kv"}


@dataclass(frozen=True)
class Scaffold:
    source: Path  # the package dc new-plugin wrote
    site: Path  # where pip installed it
    env: dict[str, str]  # DC's environment with the package installed


def installed_env(site: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [env.get("PYTHONPATH", ""), str(site)]))
    return env


def pip_install(source: Path, site: Path) -> None:
    pip = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index"]
    subprocess.run(
        [*pip, "--target", str(site), str(source)],
        check=True,
        capture_output=True,
    )


@pytest.fixture(scope="module")
def scaffold(tmp_path_factory: pytest.TempPathFactory) -> Scaffold:
    work = tmp_path_factory.mktemp("plugins")
    for kind, name in PLUGINS.items():
        made = dc("new-plugin", kind, name, "--dir", str(work))
        assert made.returncode == 0, made.stderr
        assert f"dc check-plugin {name}" in made.stdout
    source = work / "my-robot-dc"
    site = tmp_path_factory.mktemp("site")
    pip_install(source, site)
    return Scaffold(source, site, installed_env(site))


def test_each_scaffolded_kind_keeps_the_plugin_contract(scaffold: Scaffold) -> None:
    # DC's own plugins are checked the same way.
    checked = dc("check-plugin", *PLUGINS.values(), "dc_measurements/Uptime", env=scaffold.env)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert checked.stdout.count("keeps DC's plugin contract") == 4, checked.stdout
    assert "FAILED" not in checked.stdout
    for check in ("page examples", "schema", "topic left to the server", "lifecycle"):
        assert f"  ok      {check}\n" in checked.stdout


def test_the_scaffolded_package_is_lint_clean_and_its_own_tests_pass(scaffold: Scaffold) -> None:
    # The rules DC holds its own code to; an author starting from the scaffold starts clean.
    ruff = [str(BIN / "ruff")]
    rules = ["--no-cache", "--select", "E,F,W,I,B,UP,SIM,RUF", "--line-length", "120", "--target-version", "py311"]
    lint = subprocess.run([*ruff, "check", *rules, "."], cwd=scaffold.source, capture_output=True, text=True)
    assert lint.returncode == 0, lint.stdout
    formatted = subprocess.run(
        [*ruff, "format", "--no-cache", "--check", "--line-length", "120", "."],
        cwd=scaffold.source,
        capture_output=True,
        text=True,
    )
    assert formatted.returncode == 0, formatted.stdout
    tests = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", PACKAGE],
        cwd=scaffold.source,
        env=scaffold.env,
        capture_output=True,
        text=True,
    )
    assert tests.returncode == 0 and "3 passed" in tests.stdout, tests.stdout + tests.stderr


def test_a_measurement_without_its_schema_breaks_the_contract_and_says_where(
    scaffold: Scaffold, tmp_path: Path
) -> None:
    # The installed package, as pip would have installed it from a source folder without the schema.
    shutil.copytree(scaffold.site, tmp_path / "site")
    (tmp_path / "site" / PACKAGE / "battery_level" / "schema.json").unlink()
    checked = dc("check-plugin", PLUGINS["measurement"], env=installed_env(tmp_path / "site"))
    assert checked.returncode == 1
    where = tmp_path / "site" / PACKAGE / "battery_level" / "schema.json"
    assert f"  FAILED  schema: no {where}: a measurement's schema.json sits beside its module\n" in checked.stdout
    assert "breaks DC's plugin contract (1 of 6 checks failed)" in checked.stdout


def test_check_plugin_names_an_unknown_plugin_and_new_plugin_refuses_a_bad_name(
    scaffold: Scaffold, tmp_path: Path
) -> None:
    unknown = dc("check-plugin", "my_robot_dc/BateryLevel", env=scaffold.env)
    assert unknown.returncode == 2
    assert "no installed plugin 'my_robot_dc/BateryLevel' (did you mean" in unknown.stderr
    assert "my_robot_dc/BatteryLevel" in unknown.stderr
    bad = dc("new-plugin", "measurement", "Battery", "--dir", str(tmp_path))
    assert bad.returncode == 2 and "a plugin is named PACKAGE/Class" in bad.stderr
    again = dc("new-plugin", "destination", PLUGINS["destination"], "--dir", str(scaffold.source.parent))
    assert again.returncode == 2 and "exists already" in again.stderr


def test_dc_own_contract_suite_ignores_a_plugin_package_installed_beside_dc(scaffold: Scaffold) -> None:
    # A third-party page is not linked from DC's docs, nor has DC's sections: DC's suite must not ask it
    # to. Collected with the package installed, DC's contract suite has no test of its plugins.
    pytest_ = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--collect-only"]
    suite = subprocess.run(
        [*pytest_, "tests/test_plugin_contract.py"], cwd=REPO, env=scaffold.env, capture_output=True, text=True
    )
    assert suite.returncode == 0, suite.stdout[-3000:]
    collected = [line for line in suite.stdout.splitlines() if "::" in line]
    assert any("[dc_measurements/Uptime]" in test for test in collected)
    assert not [test for test in collected if "my_robot_dc" in test]
