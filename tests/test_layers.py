"""The layers of DC's packages, read from their import statements (issue 25, item 8).

dc_core is the lowest layer; the server and plugin packages sit on it side by side and know nothing of
each other (what one server needs of another's configuration goes through dc_core, e.g.
dc_core.topics.published_topics); the dashboard is above them, and dc_bringup, which starts and
validates everything, at the top. Within that: a plugin does not import a server or its configuration,
and no two modules import each other, directly or round a longer circle.

Every import counts, also one inside a function (a lazy import is still a dependency). Test modules
inside the packages (``test_*.py``) are left out of the layers: a test may use anything, e.g.
dc_bringup.local_servers to start a real PostgreSQL.
"""

from __future__ import annotations

import ast
import tomllib
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

# Lowest first. Packages of one layer do not import each other.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("dc_core",),
    ("dc_conditions", "dc_measurements", "dc_group", "dc_destinations", "dc_sim"),
    ("dc_dashboard",),
    ("dc_bringup",),
)
RANK = {package: rank for rank, packages in enumerate(LAYERS) for package in packages}

Graph = Mapping[str, set[str]]


def modules(root: Path) -> dict[str, Path]:
    """Every module of the layered packages under ``root``, by dotted name."""
    found = {}
    for package in RANK:
        for file in sorted((root / package).rglob("*.py")):
            parts = list(file.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = file
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the modules of the layered packages it imports (a name imported from a module is an edge
    to that module: ``from dc_core.qos import SENSOR_QOS`` is one to dc_core.qos)."""
    known = modules(root)

    def resolve(name: str) -> str | None:
        while name and name not in known:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, file in known.items():
        package = module if file.name == "__init__.py" else module.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(file.read_text(), str(file))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parent = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join([*parent, base] if base else parent)
                # `from a import b`: the module a.b when there is one, else the name b of module a.
                names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
            else:
                continue
            targets |= {t for t in map(resolve, names) if t is not None and t != module}
        graph[module] = targets
    return graph


def is_test(module: str) -> bool:
    return module.rpartition(".")[2].startswith("test_")


def upward_imports(graph: Graph) -> list[str]:
    """Imports of a package of the same layer or of a higher one (test modules left out)."""
    found = []
    for module, targets in sorted(graph.items()):
        for target in sorted(targets):
            source_package, target_package = module.partition(".")[0], target.partition(".")[0]
            if is_test(module) or source_package == target_package:
                continue
            if RANK[target_package] >= RANK[source_package]:
                found.append(f"{module} -> {target}")
    return found


def plugin_modules(root: Path, graph: Graph) -> set[str]:
    """The modules of the plugins pyproject.toml registers (each entry point's module and its submodules)."""
    groups = tomllib.loads((root / "pyproject.toml").read_text())["project"]["entry-points"]
    entry_modules = {target.partition(":")[0] for group in groups.values() for target in group.values()}
    return {m for m in graph if any(m == e or m.startswith(e + ".") for e in entry_modules)}


def server_modules(graph: Graph) -> set[str]:
    """A server (it imports the lifecycle of DC's servers) or a server's configuration."""
    return {m for m, targets in graph.items() if "dc_core.lifecycle" in targets} | {
        m for m in graph if m.rpartition(".")[2] in ("server", "config") and m.partition(".")[0] != "dc_core"
    }


def plugins_on_servers(plugins: Iterable[str], graph: Graph) -> list[str]:
    servers = server_modules(graph)
    return [
        f"{module} -> {target}"
        for module in sorted(plugins)
        if not is_test(module)
        for target in sorted(graph[module] & servers)
    ]


def circles(graph: Graph) -> list[list[str]]:
    """Each set of modules that import each other, directly or round a circle (strongly connected
    components of more than one module, Tarjan's algorithm without recursion)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


# -- DC's packages --------------------------------------------------------------------------------
def test_every_package_of_dc_has_a_layer() -> None:
    # A new package left out of LAYERS would be left out of every check below.
    packages = {init.parent.name for init in REPO.glob("*/__init__.py")}
    assert packages == set(RANK)


@pytest.fixture(scope="module")
def graph() -> Graph:
    """DC's import graph, read once for the checks of this module."""
    return import_graph(REPO)


def test_no_package_imports_one_of_its_layer_or_above(graph: Graph) -> None:
    assert set(RANK) <= {m.partition(".")[0] for m in graph}, "a layered package has no module"
    assert upward_imports(graph) == []


def test_no_modules_import_each_other(graph: Graph) -> None:
    assert circles(graph) == []


def test_no_plugin_imports_a_server_or_its_configuration(graph: Graph) -> None:
    plugins = plugin_modules(REPO, graph)
    assert "dc_measurements.tcp_health" in plugins and "dc_measurements.server" in server_modules(graph)
    assert plugins_on_servers(plugins, graph) == []


# -- the checks themselves find what they are for ---------------------------------------------------
def test_the_checks_find_an_import_upwards_and_between_siblings() -> None:
    graph = {
        "dc_core.topics": {"dc_measurements.config"},  # up
        "dc_destinations.server": {"dc_group.config", "dc_core.topics"},  # sibling, then down
        "dc_dashboard.settings": {"dc_bringup.validate"},  # up
        "dc_destinations.tcp.test_tcp": {"dc_bringup.validate"},  # a test: allowed
        "dc_bringup.cli": {"dc_dashboard.cli"},  # down
    }
    assert upward_imports(graph) == [
        "dc_core.topics -> dc_measurements.config",
        "dc_dashboard.settings -> dc_bringup.validate",
        "dc_destinations.server -> dc_group.config",
    ]


def test_the_checks_find_circles_direct_and_round() -> None:
    graph = {
        "a.indexes": {"a.queries"},
        "a.queries": {"a.indexes", "a.settings"},
        "a.settings": set(),
        "b.one": {"b.two"},
        "b.two": {"b.three"},
        "b.three": {"b.one"},
    }
    assert sorted(circles(graph)) == [["a.indexes", "a.queries"], ["b.one", "b.three", "b.two"]]


def test_a_lazy_relative_or_package_import_is_an_edge(tmp_path: Path) -> None:
    (tmp_path / "dc_core").mkdir()
    (tmp_path / "dc_core" / "__init__.py").write_text("")
    (tmp_path / "dc_core" / "qos.py").write_text("def f():\n    from . import topics\n")
    (tmp_path / "dc_core" / "topics.py").write_text("from dc_core import qos\n")
    graph = import_graph(tmp_path)
    assert graph["dc_core.qos"] == {"dc_core.topics"} and graph["dc_core.topics"] == {"dc_core.qos"}
    assert circles(graph) == [["dc_core.qos", "dc_core.topics"]]
