"""Which files a record may make DC read, upload and delete, and which object keys it may write.

A record is not a trusted source: anyone who can publish on the robot's ROS graph can write one
(docs/security.md). The file destinations (MinIO/S3Files, FilesMetrics) therefore take the paths a
record names only inside ``allowed_roots`` — by default the folder the measurement server saves its
files in — and only files that DC's own user owns and that have no other name (a hard link made
inside the root to a file outside would otherwise pass). The file is opened once, without
following a final symbolic link, and everything after the check (size, checksum, upload, deletion)
uses that open file, so a path swapped between the check and the read changes nothing.

Object keys are confined the same way: under ``key_prefix``, with no ``..``, ``.``, empty segment
or backslash (a bucket synchronised to a disk would turn those into paths).
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.errors import ConfigError
from dc_core.params import param
from dc_core.paths import DEFAULT_SAVE_BASE_PATH, expand_env, expand_values, fixed_prefix

# Read-only, never the controlling terminal, never blocking on a FIFO, never through a final symlink.
_OPEN_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
_PROC_FD = "/proc/self/fd"


class FileRefused(Exception):
    """A record named a file or key DC must not touch; the message says which and why (no secret in it)."""


def _roots_problem(roots: list[str]) -> str | None:
    for root in roots:
        if not root.strip():
            return "a list of folders (an entry is empty)"
        if os.path.normpath(root) == "/":
            return 'a list of the folders DC saves files in: "/" would let a record name any file'
    return None


def _prefix_problem(prefix: str) -> str | None:
    if not prefix:
        return None
    try:
        check_key(prefix.rstrip("/") + "/x", "")
    except FileRefused as exc:
        return f'an object key prefix such as "C3PO/" ({exc})'
    return None


@dataclass(frozen=True, kw_only=True, repr=False)
class ConfinementParams:
    """Parameters of a destination that reads (and may delete) the files records name."""

    allowed_roots: list[str] = param(
        [],
        check=_roots_problem,
        doc="Folders the files a record names must be in ($ENV); empty: measurement_server's save_local_base_path",
    )
    key_prefix: str = param(
        "", check=_prefix_problem, doc='Object keys a record names must start with this ("C3PO/"); empty: any key'
    )


def confinement_of(params: ConfinementParams) -> Confinement:
    """The checks ``params`` ask for: ``allowed_roots`` ($ENV expanded), or when it is empty the
    measurement server's default save folder (destination_server fills in its own file's one)."""
    if params.allowed_roots:
        roots = [expand_env(root, f"allowed_roots[{i}]") for i, root in enumerate(params.allowed_roots)]
    else:
        roots = default_roots(None)
    return Confinement(roots, params.key_prefix)


def check_key(key: str, prefix: str) -> str:
    """``key`` if a record may write it (under ``prefix``); :class:`FileRefused` otherwise."""
    if "\\" in key:
        raise FileRefused(f"object key {key!r} holds a backslash")
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in key):
        raise FileRefused(f"object key {key!r} holds a control character")
    for segment in key.split("/"):
        if segment in ("", ".", ".."):
            raise FileRefused(f"object key {key!r} has an empty, '.' or '..' segment")
    if prefix and not key.startswith(prefix):
        raise FileRefused(f"object key {key!r} is not under key_prefix {prefix!r}")
    return key


def default_roots(measurement_server: dict[str, Any] | None) -> list[str]:
    """The folder the measurement server of the same parameter file saves files in: its
    ``save_local_base_path`` expanded as it expands it (``$ENV``, ``=param``), cut before the first
    folder with a strftime token (``$HOME/ros2/data/%Y/%m`` -> ``$HOME/ros2/data``), absolute from
    this process's working folder (dc-bringup starts every server in the same one).

    Raises ConfigError (with the measurement server's YAML path) when it does not expand.
    """
    section = measurement_server or {}
    where = "measurement_server.save_local_base_path"
    value = section.get("save_local_base_path", DEFAULT_SAVE_BASE_PATH)
    if not isinstance(value, str):
        raise ConfigError(where, f"expected a string, got {value!r}")

    def top_level_string(name: str) -> str | None:
        found = section.get(name)
        return found if isinstance(found, str) else None

    expanded = expand_values(expand_env(value, where), top_level_string, where)
    root = os.path.abspath(fixed_prefix(expanded) or ".")
    if root == "/":
        raise ConfigError(
            where, f"{value!r} leaves no fixed folder to confine files to: set allowed_roots of the file destinations"
        )
    return [root]


def _inside(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip("/") + "/")


@dataclass(frozen=True)
class OpenedFile:
    """A file a record named, opened after it passed the checks; ``status`` is the open file's fstat."""

    path: str  # as the record named it
    real_path: str
    fd: int
    status: os.stat_result

    @property
    def size(self) -> int:
        return self.status.st_size

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)

    def reader(self) -> Iterator[bytes]:
        """The content in chunks, from the start (the open file, whatever the path names now)."""
        offset = 0
        while chunk := os.pread(self.fd, 1024 * 1024, offset):
            offset += len(chunk)
            yield chunk


class Confinement:
    """The checks of one destination: its roots (realpath'd at each check: a root may appear later) and key prefix."""

    def __init__(self, roots: Sequence[str], key_prefix: str = "") -> None:
        self.roots = [os.path.abspath(root) for root in roots]
        self.key_prefix = key_prefix
        self.uid = os.geteuid()

    def describe(self) -> str:
        return ", ".join(self.roots)

    def _real_roots(self) -> list[str]:
        return [os.path.realpath(root) for root in self.roots]

    def check_path(self, path: str) -> str:
        """The real path of ``path`` when it lies in a root (the file need not exist); :class:`FileRefused` if not."""
        if "\x00" in path:
            raise FileRefused(f"{path!r} is not a path")
        real = os.path.realpath(os.path.abspath(path))
        if not any(_inside(real, root) for root in self._real_roots()):
            raise FileRefused(f"{path} is outside allowed_roots ({self.describe()})")
        return real

    def open(self, path: str) -> OpenedFile | None:
        """The file at ``path``, opened and checked; None when there is no such file.

        :class:`FileRefused` when it is outside the roots, not a regular file, not owned by DC's
        user, has other hard links, or was replaced by a symbolic link after the check;
        OSError (EACCES…) when it cannot be opened.
        """
        real = self.check_path(path)
        try:
            fd = os.open(real, _OPEN_FLAGS)
        except (FileNotFoundError, NotADirectoryError):
            return None
        except OSError as exc:
            if exc.errno == getattr(os, "ELOOP", 40):
                raise FileRefused(f"{path} became a symbolic link") from None
            raise
        try:
            opened = self._checked(path, real, fd)
        except BaseException:
            os.close(fd)
            raise
        return opened

    def _checked(self, path: str, real: str, fd: int) -> OpenedFile:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise FileRefused(f"{path} is not a regular file")
        # What was opened, not what the path names now: a folder swapped for a link meanwhile shows here.
        with contextlib.suppress(OSError):
            opened_path = os.readlink(f"{_PROC_FD}/{fd}")
            if not any(_inside(opened_path, root) for root in self._real_roots()):
                raise FileRefused(f"{path} led outside allowed_roots when opened ({opened_path})")
        if status.st_uid != self.uid:
            raise FileRefused(f"{path} is owned by uid {status.st_uid}, not by DC's user (uid {self.uid})")
        if status.st_nlink != 1:
            raise FileRefused(f"{path} has {status.st_nlink} hard links: it may be a file from elsewhere")
        return OpenedFile(path, real, fd, status)

    def check_key(self, key: str) -> str:
        return check_key(key, self.key_prefix)


def delete_opened(opened: OpenedFile) -> bool:
    """Unlink the name the file was opened by, only if it still names the same file; False when it does not
    (another file took the name: it is left alone). OSError when the unlink fails."""
    folder, name = os.path.split(opened.real_path)
    dir_fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        try:
            now = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
        except FileNotFoundError:
            return False
        if (now.st_dev, now.st_ino) != (opened.status.st_dev, opened.status.st_ino):
            return False
        os.unlink(name, dir_fd=dir_fd)
        return True
    finally:
        os.close(dir_fd)
