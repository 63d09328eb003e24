"""Loading a DC parameter file (ROS 2 parameter YAML: ``<server>: ros__parameters: ...``)."""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from dc_core.errors import ConfigError
from dc_core.node_params import ServerNodeParams

SERVERS = ("measurement_server", "group_server", "destination_server", "image_services")
# How alike (difflib ratio) a top-level key must be to a server's name to be taken for a typo of it:
# "destination_sever" is 0.97, Nav2's "controller_server" 0.69 from "group_server".
TYPO_SIMILARITY = 0.85
# Fluent Bit's references to the environment in its configuration: ${NAME} (braces required, so that
# $TAG in an S3 key format or $HOME in a path keep their own meaning); $${ writes a literal ${.
_INTEGER = re.compile(r"-?(0|[1-9][0-9]*)")
_REFERENCE = re.compile(r"\$(\$?)\{([A-Za-z_][A-Za-z0-9_]*)\}")


def nest_dotted_keys(mapping: Mapping[str, Any], path: str = "") -> dict[str, Any]:
    """ROS parameter files may write ``flb.flush: 1`` or ``flb: {flush: 1}``; make both nested."""
    out: dict[str, Any] = {}
    for raw_key, value in mapping.items():
        key = str(raw_key)
        parts = key.split(".")
        node = out
        for i, part in enumerate(parts[:-1]):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(f"{path}.{'.'.join(parts[: i + 1])}".lstrip("."), "is both a value and a section")
            node = child
        leaf = parts[-1]
        if isinstance(value, Mapping):
            nested = nest_dotted_keys(value, f"{path}.{key}".lstrip("."))
            existing = node.get(leaf)
            if isinstance(existing, dict):
                existing.update(nested)
            else:
                node[leaf] = nested
        else:
            node[leaf] = value
    return out


@dataclass(frozen=True)
class ParamSection:
    """The ``ros__parameters`` of one node name of a parameter source (a file, or ``-p``)."""

    node: str
    """As rcl keys it: ``/ns/name``, ``/**``, ``/*/name``; or a bare ``name`` (DC's own file only, see
    :func:`node_name_matches`)."""
    params: dict[str, Any]
    """Dotted keys nested."""
    source: str
    """The file, or ``--ros-args -p``, for messages."""


def read_sections(path: str | Path, *, dc_file: bool = True) -> list[ParamSection]:
    """The node sections of a ROS 2 parameter file, as rcl reads it.

    Nested node keys are joined as a namespace path (``r1: measurement_server:`` and
    ``/r1/measurement_server:`` are one node name); a name written twice is one section, at the place
    of its first appearance, its later keys overriding the earlier ones — rcl's order, which decides
    what wins when several sections match one node (:func:`merged_params`). ``dc_file`` keeps a
    bare single name (``measurement_server:``, every DC file so far) distinct from ``/measurement_server``:
    DC resolves it in dc-bringup's ``--namespace`` (:func:`node_name_matches`).
    """
    file = Path(path)
    try:
        text = file.read_text()
    except OSError as exc:
        raise ConfigError("", f"cannot read parameter file {str(file)!r}: {exc.strerror}") from exc
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError("", f"{file}: invalid YAML{where}: {problem}") from exc
    if document is None:
        raise ConfigError("", f"{file}: the file is empty")
    if not isinstance(document, Mapping):
        raise ConfigError("", f"{file}: expected a mapping of server names at the top level")
    sections: dict[str, ParamSection] = {}
    _collect_sections(document, [], sections, str(file), dc_file)
    return list(sections.values())


def _collect_sections(
    mapping: Mapping[Any, Any], prefix: list[str], out: dict[str, ParamSection], source: str, dc_file: bool
) -> None:
    for raw_key, body in mapping.items():
        key = str(raw_key)
        if key == "ros__parameters":
            continue  # this level's own parameters: taken by the caller
        tokens = [*prefix, *(t for t in key.split("/") if t)]
        written = "/".join(tokens)
        base = tokens[-1] if tokens else key
        if base not in SERVERS and not _is_wildcard(base):
            # Other nodes' sections may share a ROS parameter file and are not DC's business (Nav2's
            # controller_server, map_server...); a name a typo away from a server's is a server
            # whose whole section would be ignored.
            typo_of = difflib.get_close_matches(base, SERVERS, n=1, cutoff=TYPO_SIMILARITY)
            if typo_of:
                raise ConfigError(
                    written, f'not a DC server section (did you mean "{typo_of[0]}"?): it would be ignored'
                )
        if not isinstance(body, Mapping):
            if base in SERVERS:
                raise ConfigError(written, "expected a 'ros__parameters' mapping")
            continue  # another node's business, even malformed
        if "ros__parameters" in body:
            params = body["ros__parameters"]
            if params is None:
                params = {}
            if not isinstance(params, Mapping):
                raise ConfigError(f"{written}.ros__parameters", "expected a mapping")
            bare = dc_file and not prefix and not key.startswith("/") and len(tokens) == 1 and not _is_wildcard(base)
            node = written if bare else "/" + written
            nested = nest_dotted_keys(params, written)
            if node in out:
                out[node] = ParamSection(node, merge_params(out[node].params, nested), source)
            else:
                out[node] = ParamSection(node, nested, source)
        elif base in SERVERS:
            raise ConfigError(written, "expected a 'ros__parameters' mapping")
        _collect_sections(body, tokens, out, source, dc_file)


def _is_wildcard(token: str) -> bool:
    return token in ("*", "**")


def node_name_matches(pattern: str, fqn: str) -> bool:
    """Whether a section keyed ``pattern`` applies to the node ``fqn`` (``/ns/name``), as rcl decides.

    ``/*`` stands for one token, ``/**`` for any number of them, none included (rclcpp and rclpy
    turn the key into a regular expression, ``/*`` -> ``(/\\w+)``, and match it with the whole name).
    A bare ``name`` (no slash: the sections of every DC file so far) is DC's: the server of that
    name in whatever namespace it runs (rcl would read ``/name``, the root namespace only), so that
    one file serves dc-bringup with and without ``--namespace``.
    """
    if "/" not in pattern:
        return fqn.rsplit("/", 1)[-1] == pattern
    wildcards = {"/**": r"(/\w+)*", "/*": r"(/\w+)"}
    expression = "".join(wildcards.get(part) or re.escape(part) for part in re.split(r"(/\*\*|/\*)", pattern))
    return re.fullmatch(expression, fqn) is not None


def node_fqn(namespace: str, name: str) -> str:
    """``/ns/name`` (``/name`` in the root namespace)."""
    space = namespace.strip("/")
    return f"/{space}/{name}" if space else f"/{name}"


def merge_params(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` over ``base`` key by key (rcl sets parameters one dotted name at a time)."""
    out = dict(base)
    for key, value in override.items():
        existing = out.get(key)
        if isinstance(existing, dict) and isinstance(value, Mapping):
            out[key] = merge_params(existing, value)
        else:
            out[key] = value
    return out


@dataclass
class ParamsFile:
    """What a DC parameter file (with the ``--ros-args`` parameters after it) gives each server."""

    servers: dict[str, dict[str, Any]]
    """Server name -> its parameters: every section that matches it, merged in order."""
    ignored: list[str] = field(default_factory=list)
    """Sections of DC's file that match none of its servers (other nodes', another namespace's)."""
    raw: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Server name -> its parameters before ``${NAME}`` references are replaced (what may be shown)."""


def load_params(
    path: str | Path,
    namespace: str = "",
    ros_sections: Sequence[ParamSection] = (),
    environ: Mapping[str, str] | None = None,
) -> ParamsFile:
    """The servers a DC parameter file runs under ``namespace``, and each one's parameters.

    A server runs when DC's file has a section naming it (wildcards in the namespace allowed:
    ``/**/measurement_server``) that matches it; a section of wildcards alone (``/**``) adds
    parameters to the servers that run but starts none, and only those each server has.
    ``ros_sections`` (``--params-file`` and ``-p`` of ``--ros-args``, :mod:`dc_core.ros_args`) come
    after the file's sections: on the command line, as for any ROS node, they win.
    """
    file = Path(path)
    sections = read_sections(file)
    fqns = {server: node_fqn(namespace, server) for server in SERVERS}
    running = [
        server
        for server in SERVERS
        if any(s.node.rsplit("/", 1)[-1] == server and node_name_matches(s.node, fqns[server]) for s in sections)
    ]
    if not running:
        where = f" for nodes in namespace {node_fqn(namespace, '').rstrip('/') or '/'}" if namespace.strip("/") else ""
        raise ConfigError("", f"{file}: no DC server section{where} (expected one of {', '.join(SERVERS)})")
    servers: dict[str, dict[str, Any]] = {}
    raw: dict[str, dict[str, Any]] = {}
    every_server = {f.name for f in fields(ServerNodeParams)}
    for server in running:
        matching = [s for s in [*sections, *ros_sections] if node_name_matches(s.node, fqns[server])]
        own = [s for s in matching if s.node.rsplit("/", 1)[-1] == server]
        # A ROS node ignores the overrides of parameters it does not declare: a wildcard section
        # (/**, -p without a node) sets on each server only what it has — the parameters of every
        # server, and the top-level keys its own sections write (a plugin's section, flb).
        has = every_server.union(*(s.params for s in own))
        merged: dict[str, Any] = {}
        for section in matching:
            given = section.params if section in own else {k: v for k, v in section.params.items() if k in has}
            merged = merge_params(merged, given)
        raw[server] = merged
        servers[server] = expand_references(merged, server, environ)
    ignored = [s.node for s in sections if not any(node_name_matches(s.node, fqns[server]) for server in running)]
    return ParamsFile(servers, ignored, raw)


def load_params_file(
    path: str | Path, namespace: str = "", ros_sections: Sequence[ParamSection] = ()
) -> dict[str, dict[str, Any]]:
    """Server name -> its parameters (:func:`load_params`)."""
    return load_params(path, namespace, ros_sections).servers


class UnsetShown(Mapping[str, str]):
    """The environment, where a variable that is not set reads as ``<NAME unset>`` and is remembered in
    ``unset``: for the tools that read a parameter file without running it (``dc status --params``)
    in a shell that lacks the service's secrets."""

    def __init__(self, environ: Mapping[str, str] = os.environ) -> None:
        self._environ = environ
        self.unset: set[str] = set()

    def __getitem__(self, name: str) -> str:
        if name in self._environ:
            return self._environ[name]
        self.unset.add(name)
        return f"<{name} unset>"

    def __contains__(self, name: object) -> bool:
        return True

    def __iter__(self) -> Any:
        return iter(self._environ)

    def __len__(self) -> int:
        return len(self._environ)


def expand_references(value: Any, path: str, environ: Mapping[str, str] | None = None) -> Any:
    """``${NAME}`` in every string of a parameter tree replaced by the environment variable NAME.

    Secrets (passwords, keys) can then live in the environment of the robot's service rather than in
    a parameter file. An unset variable is a configuration error naming the key: an empty password
    sent to a server would fail later and less clearly.
    """
    env = os.environ if environ is None else environ
    if isinstance(value, str):
        whole = _REFERENCE.fullmatch(value)
        if whole and not whole.group(1) and _INTEGER.fullmatch(env.get(whole.group(2), "")):
            # `port: ${DC_POSTGRES_PORT}` is an integer, as `port: 15432` would be. Only integers
            # written as YAML would read them back unchanged ("0123" or "1.50" stay text).
            return int(env[whole.group(2)])

        def replace(match: re.Match[str]) -> str:
            escaped, name = match.group(1), match.group(2)
            if escaped:
                return "${" + name + "}"
            if name not in env:
                raise ConfigError(path, f"environment variable {name} is not set (referenced as ${{{name}}})")
            return env[name]

        return _REFERENCE.sub(replace, value)
    if isinstance(value, Mapping):
        return {key: expand_references(item, f"{path}.{key}", env) for key, item in value.items()}
    if isinstance(value, list):
        return [expand_references(item, f"{path}[{i}]", env) for i, item in enumerate(value)]
    return value
