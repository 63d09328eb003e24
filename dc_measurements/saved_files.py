"""Where measurements that save files (Map, Camera) put them, and how they write them.

Local path: ``save_local_base_path / all_base_path / save_path``; remote path per ``remote_keys``
entry: ``all_base_path / <its remote_prefixes entry> / save_path`` without a leading ``/`` (the
object key a storage destination uploads to). strftime tokens (in all three) are expanded with the
time the file is saved (the node's clock: simulated time under ``use_sim_time``), in local time, as the original.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from dc_core.measurement import BasePaths
from dc_core.paths import expand_time


@dataclass(frozen=True)
class FileLocations:
    """A file's base path without extension, locally and per remote storage key."""

    local: str
    remote: dict[str, str]

    def with_suffix(self, suffix: str) -> tuple[str, dict[str, str]]:
        return self.local + suffix, {key: path + suffix for key, path in self.remote.items()}


def file_locations(paths: BasePaths, save_path: str, when_s: float) -> FileLocations:
    relative = expand_time(save_path, when_s)
    common = expand_time(paths.all_base_path, when_s)
    local = os.path.join(expand_time(paths.save_local_base_path, when_s), common, relative)
    remote = {
        key: "/".join(part.strip("/") for part in (common, expand_time(prefix, when_s), relative) if part.strip("/"))
        for key, prefix in paths.remote_prefixes.items()
    }
    return FileLocations(local, remote)


def unused_locations(locations: FileLocations, suffixes: tuple[str, ...]) -> FileLocations:
    """``locations``, or with ``-1``, ``-2``… appended, so that no file of an earlier sample saved in the same
    second is overwritten (its record points at it)."""
    candidate, n = locations, 0
    while any(os.path.exists(candidate.local + suffix) for suffix in suffixes):
        n += 1
        candidate = FileLocations(
            f"{locations.local}-{n}", {key: f"{path}-{n}" for key, path in locations.remote.items()}
        )
    return candidate


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
