"""Expansion of configured paths: ``$ENV``/``${ENV}``, ``=param`` and strftime tokens."""

from __future__ import annotations

import datetime as dt
import os
import re
import time
import zoneinfo
from collections.abc import Callable, Mapping
from pathlib import Path

from dc_core.errors import ConfigError

# The measurement server's save_local_base_path when none is given; the file destinations confine the
# files records name to its fixed part by default (dc_core.confined_files.default_roots).
DEFAULT_SAVE_BASE_PATH = "$HOME/ros2/data/%Y/%m/%d/%H"

_ENV = re.compile(r"\$\{([A-Za-z_]\w*)\}|\$([A-Za-z_]\w*)")
_VALUE = re.compile(r"=\{([A-Za-z_]\w*)\}|=([A-Za-z_]\w*)")


def expand_env(text: str, path: str = "", environ: Mapping[str, str] | None = None) -> str:
    """Replace ``$NAME`` and ``${NAME}``; an unset variable is a configuration error."""
    env = os.environ if environ is None else environ

    def repl(match: re.Match[str]) -> str:
        name = match.group(1) or match.group(2)
        if name not in env:
            raise ConfigError(path, f"environment variable ${name} is not set (in {text!r})")
        return env[name]

    return _ENV.sub(repl, text)


def expand_values(text: str, lookup: Callable[[str], str | None], path: str = "") -> str:
    """Replace ``=name`` by the string value ``lookup(name)``; an unknown name is an error."""

    def repl(match: re.Match[str]) -> str:
        name = match.group(1) or match.group(2)
        value = lookup(name)
        if value is None:
            raise ConfigError(path, f"'={name}' names no string parameter")
        return value

    return _VALUE.sub(repl, text)


PATHS_TIMEZONES = "utc, local or a zone name such as Europe/Paris"


def zone_problem(name: str) -> str | None:
    """Why ``name`` is no ``paths_timezone`` (None when it is one): a check for dc_core.params."""
    try:
        path_zone(name)
    except ValueError as exc:
        return str(exc)
    return None


def path_zone(name: str) -> dt.tzinfo | None:
    """The zone of ``paths_timezone``: UTC for ``utc``, None for ``local`` (the machine's zone at each
    moment, as the original), else the IANA zone so named; ValueError for a name the system does not know."""
    if name.lower() == "utc":
        return dt.UTC
    if name.lower() == "local":
        return None
    try:
        return zoneinfo.ZoneInfo(name)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError):
        raise ValueError(f"expected {PATHS_TIMEZONES}; no time zone is named {name!r}") from None


def expand_time(text: str, when: float | None = None, zone: dt.tzinfo | None = dt.UTC) -> str:
    """strftime expansion of ``when`` (now by default) in ``zone`` (None: the machine's local time).

    Every strftime of a saved file's path or an object key goes through here, so that all of them
    say the same hour for the same moment."""
    moment = time.time() if when is None else when
    if zone is None:
        return time.strftime(text, time.localtime(moment))
    return dt.datetime.fromtimestamp(moment, zone).strftime(text)


def fixed_prefix(path: str) -> str:
    """The folders of ``path`` before the first one with a strftime token: the same at every hour."""
    kept: list[str] = []
    for part in path.split("/"):
        if "%" in part:
            break
        kept.append(part)
    prefix = "/".join(kept)
    return "/" if not prefix and path.startswith("/") else prefix


def data_home() -> Path:
    """``$XDG_DATA_HOME``, else ``~/.local/share``: where DC keeps what must outlive its processes."""
    return Path(os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share"))


def instance_dir(kind: str, namespace: str = "/", domain_id: str | None = None) -> Path:
    """``<data home>/dc/<kind>/domain-<ROS_DOMAIN_ID>/<namespace>/``: one folder per DC instance (ROS domain
    ``domain_id``, default ``$ROS_DOMAIN_ID``, else 0 as rclpy's; ``default`` for the root namespace,
    ``ns.robot1.arm`` for ``/robot1/arm``), so that two DCs on one machine never share it."""
    domain = domain_id if domain_id is not None else os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
    parts = [part for part in namespace.split("/") if part]
    return data_home() / "dc" / kind / f"domain-{domain}" / ("ns." + ".".join(parts) if parts else "default")
