"""Where measurements that save files (Map, Camera) put them, and how they write them.

Local path: ``save_local_base_path / all_base_path / save_path``; remote path per ``remote_keys``
entry: ``all_base_path / <its remote_prefixes entry> / save_path`` without a leading ``/`` (the
object key a storage destination uploads to). strftime tokens (in all three) are expanded with the
time the file is saved (the node's clock: simulated time under ``use_sim_time``), in UTC unless
``paths_timezone`` says otherwise (``local``: the original's local time). With ``key_layout: hive`` the
object key is ``<remote prefix>/robot=<name>/date=YYYY-MM-DD/save_path``: all_base_path stays local.
"""

from __future__ import annotations

import os
import tempfile
import threading
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dc_core.measurement import BasePaths
from dc_core.paths import expand_env, expand_time, expand_values, path_zone
from dc_measurements.config import NODE_NAME, ROBOT_NAME_PARAM, MeasurementServerConfig


@dataclass(frozen=True)
class FileLocations:
    """A file's base path without extension, locally and per remote storage key."""

    local: str
    remote: dict[str, str]

    def with_suffix(self, suffix: str) -> tuple[str, dict[str, str]]:
        return self.local + suffix, {key: path + suffix for key, path in self.remote.items()}


def base_paths(
    section: dict[str, Any], config: MeasurementServerConfig, custom: list[tuple[str, str, bool]]
) -> BasePaths:
    """The server's base paths, expanded but for strftime tokens (``custom``: resolve_custom_params')."""
    node = config.node

    def top_level_string(name: str) -> str | None:
        value = section.get(name)
        return value if isinstance(value, str) else None

    custom_values = {cid: value for cid, (_, value, _) in zip(config.custom_str_params, custom, strict=True)}
    save = expand_values(
        expand_env(node.save_local_base_path, f"{NODE_NAME}.save_local_base_path"),
        top_level_string,
        f"{NODE_NAME}.save_local_base_path",
    )
    all_base = expand_values(
        expand_env(node.all_base_path, f"{NODE_NAME}.all_base_path"),
        custom_values.get,
        f"{NODE_NAME}.all_base_path",
    )
    partitions = ""
    if node.key_layout == "hive":
        # Quoted: a "/" or "=" in a robot's name must not make another folder or partition; "%%"
        # keeps the quoting's "%" from strftime.
        robot = urllib.parse.quote(custom_values[ROBOT_NAME_PARAM], safe="").replace("%", "%%")
        partitions = f"robot={robot}/date=%Y-%m-%d"
    return BasePaths(
        save_local_base_path=save,
        all_base_path=all_base,
        zone=path_zone(node.paths_timezone),
        key_partitions=partitions,
    )


def file_locations(paths: BasePaths, save_path: str, when_s: float) -> FileLocations:
    def expand(text: str) -> str:
        return expand_time(text, when_s, paths.zone)

    relative = expand(save_path)
    common = expand(paths.all_base_path)
    local = os.path.join(expand(paths.save_local_base_path), common, relative)
    remote = {}
    for key, prefix in paths.remote_prefixes.items():
        parts = (expand(prefix), expand(paths.key_partitions)) if paths.key_partitions else (common, expand(prefix))
        remote[key] = "/".join(part.strip("/") for part in (*parts, relative) if part.strip("/"))
    return FileLocations(local, remote)


class ReservedPaths:
    """Base paths handed to records whose files are not written yet (they are written once the record is
    published, on a worker): a second sample in the same second must get another name, not overwrite them."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._reserved: set[str] = set()

    def reserve(self, locations: FileLocations, suffixes: tuple[str, ...]) -> FileLocations:
        """``locations``, or with ``-1``, ``-2``… appended when taken by a reservation or an existing file."""
        candidate, n = locations, 0
        with self._lock:
            while candidate.local in self._reserved or any(
                os.path.exists(candidate.local + suffix) for suffix in suffixes
            ):
                n += 1
                candidate = FileLocations(
                    f"{locations.local}-{n}", {key: f"{path}-{n}" for key, path in locations.remote.items()}
                )
            self._reserved.add(candidate.local)
        return candidate

    def release(self, local: str) -> None:
        with self._lock:
            self._reserved.discard(local)


FileContent = bytes | Callable[[], bytes]


@dataclass
class PendingFiles:
    """The files of one sample, written when (and only if) its record is published."""

    sample: dict[str, Any]
    base: str  # the reserved local base path
    files: dict[str, FileContent] = field(default_factory=dict)  # path -> content, or what makes it

    def write(self) -> int:
        for path, content in self.files.items():
            write_atomically(path, content() if callable(content) else content)
        return len(self.files)


def write_atomically(path: str, content: bytes) -> None:
    """Write through a temporary file renamed into place: a reader (an upload) never sees half a file."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(content)
        os.replace(temporary, target)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
