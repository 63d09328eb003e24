"""Loading a DC parameter file (ROS 2 parameter YAML: ``<server>: ros__parameters: ...``)."""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from dc_core.errors import ConfigError

SERVERS = ("measurement_server", "group_server", "destination_server", "image_services")
# How alike (difflib ratio) a top-level key must be to a server's name to be taken for a typo of it:
# "destination_sever" is 0.97, Nav2's "controller_server" 0.69 from "group_server".
TYPO_SIMILARITY = 0.85
# Fluent Bit's references to the environment in its configuration: ${NAME} (braces required, so that
# $TAG in an S3 key format or $HOME in a path keep their own meaning); $${ writes a literal ${.
_INTEGER = re.compile(r"-?(0|[1-9][0-9]*)")
_REFERENCE = re.compile(r"\$(\$?)\{([A-Za-z_][A-Za-z0-9_]*)\}")


def other_sections(path: str | Path) -> list[str]:
    """Top-level keys of a parameter file that are not DC servers (other nodes' parameters, ignored)."""
    document = yaml.safe_load(Path(path).read_text())
    return [str(name) for name in document if name not in SERVERS] if isinstance(document, Mapping) else []


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


def load_params_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """Server name -> its ``ros__parameters`` mapping (dotted keys nested)."""
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
    servers: dict[str, dict[str, Any]] = {}
    for name, body in document.items():
        if name not in SERVERS:
            # Other nodes' sections may share a ROS parameter file and are not DC's business (Nav2's
            # controller_server, map_server...); a name a typo away from a server's is a server
            # whose whole section would be ignored.
            typo_of = difflib.get_close_matches(str(name), SERVERS, n=1, cutoff=TYPO_SIMILARITY)
            if typo_of:
                raise ConfigError(
                    str(name), f'not a DC server section (did you mean "{typo_of[0]}"?): it would be ignored'
                )
            continue
        if not isinstance(body, Mapping) or "ros__parameters" not in body:
            raise ConfigError(str(name), "expected a 'ros__parameters' mapping")
        params = body["ros__parameters"]
        if params is None:
            params = {}
        if not isinstance(params, Mapping):
            raise ConfigError(f"{name}.ros__parameters", "expected a mapping")
        servers[str(name)] = expand_references(nest_dotted_keys(params, str(name)), str(name))
    if not servers:
        raise ConfigError("", f"{file}: no DC server section (expected one of {', '.join(SERVERS)})")
    return servers


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
