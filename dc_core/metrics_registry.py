"""Where each running DC server serves its metrics, written down so that `dc status` and `dc top` find it.

Every server's metrics endpoint is on by default, each kind of server on its own default port. A
second DC on the machine (another ROS domain or namespace) finds those ports taken; its servers then
serve on a free port instead (dc_core.http_status), and a port chosen at start is only known to the
process that bound it. So each server writes its actual address in a small file of the runtime folder,

    $XDG_RUNTIME_DIR/dc/metrics/domain-<ROS_DOMAIN_ID>/<namespace, %-quoted>/<server>.json

(``<tmp>/dc-<uid>/...`` without ``XDG_RUNTIME_DIR``), removes it when the endpoint stops, and a reader
skips a file whose process is gone (a server killed with SIGKILL leaves its file behind). The folders
are the user's own (0700): an address is not secret, but another user must not redirect `dc status`.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from dc_core.topics import ros_namespace


def runtime_root() -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR", "").strip()
    if base:
        return Path(base) / "dc" / "metrics"
    return Path(tempfile.gettempdir()) / f"dc-{os.getuid()}" / "metrics"


def domain_id_from_env() -> int:
    """ROS_DOMAIN_ID as rcl reads it (unset or empty: 0)."""
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(text) if text.isdigit() else 0


def folder(domain_id: int, namespace: str) -> Path:
    return runtime_root() / f"domain-{domain_id}" / quote(ros_namespace(namespace), safe="")


@dataclass(frozen=True)
class Announcement:
    """A server's metrics address as written down: ``server`` is its node name (destination_server, …)."""

    server: str
    host: str
    port: int
    pid: int


def announce(server: str, domain_id: int, namespace: str, host: str, port: int) -> Path | None:
    """Write ``server``'s address (None when the folder cannot be written: `dc status` then asks the
    configured port, which is all that is lost)."""
    target = folder(domain_id, namespace)
    try:
        _own_folder(target)
        file = target / f"{server}.json"
        # Written whole then renamed: a reader never sees half a file.
        fd, temporary = tempfile.mkstemp(dir=target, prefix=f".{server}.")
        with os.fdopen(fd, "w") as out:
            json.dump({"server": server, "host": host, "port": port, "pid": os.getpid()}, out)
        os.replace(temporary, file)
        return file
    except OSError:
        return None


def _own_folder(target: Path) -> None:
    """``target`` and the folders up to the runtime root's parent made 0700; one of another user refused
    (in /tmp anyone could create ``dc-<uid>`` first)."""
    top = runtime_root().parent
    for path in [p for p in reversed(target.parents) if top in (p, *p.parents)] + [target]:
        with contextlib.suppress(FileExistsError):
            path.mkdir(mode=0o700)
        if path.stat().st_uid != os.getuid():
            raise PermissionError(f"{path} is not this user's")


def withdraw(file: Path | None) -> None:
    """Remove a file :func:`announce` wrote, if it is still this process' own."""
    if file is None:
        return
    with contextlib.suppress(OSError, ValueError):
        if json.loads(file.read_text()).get("pid") == os.getpid():
            file.unlink()


def announced(domain_id: int, namespace: str) -> dict[str, Announcement]:
    """The servers of a live process in that domain and namespace, by server name."""
    found: dict[str, Announcement] = {}
    try:
        files = sorted(folder(domain_id, namespace).glob("*.json"))
    except OSError:
        return found
    for file in files:
        try:
            data = json.loads(file.read_text())
            entry = Announcement(str(data["server"]), str(data["host"]), int(data["port"]), int(data["pid"]))
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if _alive(entry.pid):
            found[entry.server] = entry
    return found


def _alive(pid: int) -> bool:
    # DC runs on Linux (dc_bringup.instances reads /proc too); a pid of another user's process counts.
    return Path(f"/proc/{pid}").is_dir()
