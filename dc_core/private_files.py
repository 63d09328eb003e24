"""Files DC writes are its user's alone unless a setting says otherwise.

Records hold positions, QR texts and user fields; the buffer and DC's outputs used to be created
0644 in 0755 folders, readable by every local account. DC's processes therefore run under umask
077, and the files that must stay private whatever the umask of whoever started DC (the buffer
database, its lock, ffmpeg's log) are created with an explicit mode. Another account that must read
DC's files is given access by a default ACL on their folder (``setfacl -d -m g:uploader:rX``), which
new files get whatever the umask; the File destination has its own ``file_mode``.

The rule for what already exists: a file DC alone owns by its name (the buffer database and its
``-wal``/``-shm``, the buffer lock, ffmpeg's log) is set to 0600 at every start, so an upgrade
tightens what an older DC left; a folder that exists is never changed (``storage_path`` or
``save_local_base_path`` may be ``/tmp`` or a shared folder), nor an output file DC did not create.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat

PRIVATE_UMASK = 0o077
PRIVATE_FILE = 0o600
PRIVATE_FOLDER = 0o700


def use_private_umask() -> None:
    """Umask 077 for this process and the processes it starts (ffmpeg among them).

    Called first thing by dc-bringup and by each server process."""
    os.umask(PRIVATE_UMASK)


def make_folders(path: str | os.PathLike[str], mode: int = PRIVATE_FOLDER) -> None:
    """Create ``path`` and its missing parents, each with exactly ``mode`` (not reduced by the
    umask: a folder for group-readable files must be group-searchable). Folders that exist are
    left as they are."""
    target = path = os.path.abspath(os.fspath(path))
    missing: list[str] = []
    while not os.path.isdir(path):
        missing.append(path)
        parent = os.path.dirname(path)
        if parent == path:
            break
        path = parent
    for folder in reversed(missing):
        try:
            os.mkdir(folder, mode)
        except FileExistsError:
            continue  # made meanwhile by another process: theirs, left alone
        os.chmod(folder, mode)
    if not os.path.isdir(target):
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", target)


def tighten(path: str | os.PathLike[str], mode: int = PRIVATE_FILE) -> None:
    """Set the mode of a file DC owns by its name to ``mode`` when it exists and is looser.

    Not followed through a symbolic link, and only for a file of this process' user: a link
    planted in DC's folder must not turn a chmod onto another file."""
    with contextlib.suppress(OSError):
        info = os.lstat(path)
        if stat.S_ISREG(info.st_mode) and info.st_uid == os.geteuid() and stat.S_IMODE(info.st_mode) & ~mode:
            os.chmod(path, mode, follow_symlinks=False)


def create_private(path: str | os.PathLike[str], flags: int, mode: int = PRIVATE_FILE) -> int:
    """``os.open`` of a file DC owns by its name: created with ``mode``, an existing one tightened
    to it, never through a symbolic link."""
    fd = os.open(path, flags | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    try:
        info = os.fstat(fd)
        if info.st_uid == os.geteuid() and stat.S_IMODE(info.st_mode) & ~mode:
            os.fchmod(fd, mode)
    except BaseException:
        os.close(fd)
        raise
    return fd


def mode_problem(value: object) -> str | None:
    """None when ``value`` is a file mode written as a quoted octal string (``"0640"``), else what
    was expected. A YAML number is refused: YAML reads 0640 as octal and 640 as decimal, and a
    mode must not change with a leading zero."""
    expected = 'a file mode as a quoted octal string, e.g. "0600" or "0640"'
    if not isinstance(value, str):
        return expected + " (an unquoted number is ambiguous: YAML reads 0640 as octal, 640 as decimal)"
    text = value.strip().removeprefix("0o")
    if not text or any(c not in "01234567" for c in text) or int(text, 8) > 0o777:
        return expected
    return None


def parse_mode(value: str) -> int:
    """The mode a string accepted by :func:`mode_problem` stands for."""
    return int(value.strip().removeprefix("0o"), 8)


def folder_mode(file_mode: int) -> int:
    """The mode of a folder holding files of ``file_mode``: owner rwx, and r-x for whoever may read them."""
    mode = PRIVATE_FOLDER
    if file_mode & 0o040:
        mode |= 0o050
    if file_mode & 0o004:
        mode |= 0o005
    return mode


def private_database(path: str | os.PathLike[str]) -> None:
    """A SQLite database file created 0600 before SQLite opens it (SQLite gives its ``-wal`` and
    ``-shm`` the database's mode), or an existing one and its companions tightened to 0600."""
    os.close(create_private(path, os.O_RDWR))
    for suffix in ("-wal", "-shm", "-journal"):
        tighten(f"{os.fspath(path)}{suffix}")
