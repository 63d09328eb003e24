"""Where the delivery buffer lives, and the lock that gives it one owner.

``flb.storage_path`` when set; otherwise a folder of the user's data that separates what must not
mix: ``$XDG_DATA_HOME/dc/buffer/domain-<ROS_DOMAIN_ID>/<namespace>/`` (``~/.local/share`` without
XDG_DATA_HOME; ``default`` for the root namespace, ``ns.robot1.arm`` for ``/robot1/arm``). Two
robots simulated on one machine (different domains or namespaces) get two buffers. The parameter
file's path takes no part: moving or renaming it must not strand the records waiting in the buffer.

A buffer has one owner: the destination server holds an exclusive lock on ``delivery.sqlite3.lock``
beside it from configure to cleanup. A second server on the same folder (the same domain and
namespace, or the same ``storage_path``) fails configure and says who holds it; without the lock
it would send the first server's records to its own destinations (a File destination named
``out`` in both got the other's records, silently). The lock is the kernel's (``flock``): a
process killed with -9 releases it, so a restart is never blocked. ``dc buffer`` works on the
file beside a running server without the lock, as SQLite's WAL allows.

The records in the buffer are the robot's data: a folder DC creates for it is 0700, the lock 0600
(the database: :mod:`dc_destinations.buffer`). A configured folder that exists is left as it is
(it may be shared), with a warning when other accounts can list it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sqlite3
from pathlib import Path

from dc_core.errors import DcError
from dc_core.logs import Logger
from dc_core.paths import data_home, expand_env, instance_dir
from dc_core.private_files import PRIVATE_FILE, create_private, make_folders
from dc_destinations.settings import DeliveryParams

# What each storage_sync promises, as the server says it at start.
SYNC_PROMISE = {
    "normal": "committed records survive a crash of the process, a power cut may lose the last ones",
    "full": "committed records survive a crash of the process and a power cut",
}
LOCK_SUFFIX = ".lock"
STORAGE_PATH_PARAMETER = "destination_server.ros__parameters.flb.storage_path"


def legacy_storage_dir() -> Path:
    """The one default folder of DC before buffers were separated by domain and namespace."""
    return data_home() / "dc" / "buffer"


def default_storage_dir(namespace: str = "/", domain_id: str | None = None) -> Path:
    """The buffer folder of a destination server in ``namespace`` and ROS domain ``domain_id``
    (default: ``$ROS_DOMAIN_ID``, else 0, as rclpy's)."""
    return instance_dir("buffer", namespace, domain_id)


def storage_dir(settings: DeliveryParams, logger: Logger, namespace: str = "/") -> Path:
    """The buffer's folder, created; the default one when the configured folder cannot be used (logged)."""
    configured = settings.storage_path.strip()
    if not configured:
        directory = default_storage_dir(namespace)
        make_folders(directory)
        return directory
    directory = Path(os.path.expanduser(expand_env(configured, "destination_server.flb.storage_path")))
    try:
        existed = directory.is_dir()
        make_folders(directory)
        if not os.access(directory, os.W_OK | os.X_OK):
            raise PermissionError(f"{directory} is not writable")
    except OSError as exc:
        fallback = default_storage_dir(namespace)
        logger.error(f"flb.storage_path {directory} cannot be used ({exc}); buffering in {fallback} instead")
        make_folders(fallback)
        return fallback
    mode = directory.stat().st_mode & 0o777
    if existed and mode & 0o077:
        logger.warning(
            f"flb.storage_path {directory} can be listed by other accounts (mode {mode:o}); "
            f"the buffer's files are 0600, but DC leaves the modes of a folder it did not create alone: chmod 700 it"
        )
    return directory


class BufferInUse(DcError):
    """Another process owns the buffer."""


class BufferLock:
    """The exclusive lock of one buffer file; see the module documentation."""

    def __init__(self, buffer_file: Path) -> None:
        self.buffer_file = buffer_file
        self.path = buffer_file.with_name(buffer_file.name + LOCK_SUFFIX)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> None:
        """Take the lock or raise :class:`BufferInUse` naming the owner and the parameter that moves this one."""
        if self._fd is not None:
            return
        fd = create_private(self.path, os.O_RDWR, PRIVATE_FILE)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _read_owner(fd)
            os.close(fd)
            raise BufferInUse(
                f"the delivery buffer {self.buffer_file} is in use by process {owner} (another destination_server, "
                f"of another DC instance?); two servers on one buffer would deliver each other's records. Give this "
                f"one its own folder with {STORAGE_PATH_PARAMETER}, or run it in another ROS domain or namespace",
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        os.close(self._fd)  # closing the descriptor releases the flock
        self._fd = None


def _read_owner(fd: int) -> str:
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        text = ""
    return text or "unknown"


def waiting_in(buffer_file: Path) -> int:
    """Records waiting in the queues of a buffer file (0 when it is not one), read without changing it."""
    if not buffer_file.is_file():
        return 0
    read_only = f"{buffer_file.resolve().as_uri()}?mode=ro"  # a URI: a '?' or '#' in the path stays a path
    try:
        with contextlib.closing(sqlite3.connect(read_only, uri=True, timeout=1.0)) as conn:
            row = conn.execute("SELECT COALESCE(SUM(rows), 0) FROM queues").fetchone()
    except sqlite3.Error:
        return 0
    return int(row[0])
