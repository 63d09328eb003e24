"""File destination: appends records to one local file, on disk (fsync) before confirming them.

The file holds the robot's records: DC creates it with ``file_mode`` (0600 unless a team wants
group read) and the folders it creates for it so that those who may read the file can reach it.
A file that exists already keeps its mode: it may have been made by logrotate or an operator with
the mode they chose.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RetryableError, SendOutcome
from dc_core.errors import PluginError
from dc_core.params import param
from dc_core.paths import expand_env
from dc_core.private_files import folder_mode, make_folders, mode_problem, parse_mode
from dc_destinations.connection import Connection

FORMATS = ("json", "plain", "csv", "ltsv", "out_file", "template")
_TEMPLATE_FIELD = re.compile(r"\{([^{}]+)\}")


@dataclass(frozen=True, kw_only=True)
class FileParams:
    path: str = param("$HOME/data", doc="Folder of the file ($ENV and ${ENV} expanded)")
    file: str = param("", doc="File name inside `path` (default: the destination's name)")
    format: str = param(
        "json",
        choices=FORMATS,
        doc="json and plain: one JSON object per line; csv; ltsv; out_file: `<name>: [<time>, <record>]`",
    )
    mkdir: bool = param(
        True, doc="Create `path` and its parents when missing (0700, or readable as file_mode allows: 0750 for 0640)"
    )
    file_mode: int | str = param(
        "0600",
        doc='Mode of the file when DC creates it, a quoted octal string ("0640": group read)',
        check=mode_problem,
    )
    delimiter: str = param("", doc="Field separator of csv (default ',') and ltsv (default tab)")
    label_delimiter: str = param(":", doc="Separator of label and value in ltsv")
    template: str = param("{time} {message}", doc="Line of format template: {key} is a record value")


def cell(value: Any) -> str:
    """A record value as text in a csv/ltsv/template field: strings as they are, the rest as JSON."""
    if isinstance(value, str):
        return value
    if value is None:
        return ""
    return json.dumps(value, ensure_ascii=False, separators=(",", ":"))


def stamp_text(stamp_ns: int) -> str:
    seconds, nanos = divmod(stamp_ns, 1_000_000_000)
    return f"{seconds}.{nanos:09d}"


class File(Destination[FileParams]):
    """Append records to a local file (JSON lines, csv, ltsv, ...), fsynced before they are confirmed."""

    def __init__(self, context: Any, params: FileParams) -> None:
        super().__init__(context, params)
        self.file_path = ""
        self.file_mode = 0o600
        self.delimiter = ""
        # Opened again when the file was moved or deleted (log rotation): then a new one is started.
        self._fd = self.keep(Connection("", self._open, self._close, timeout=0, usable=self._same_file))
        self._columns: list[str] | None = None

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        folder = expand_env(p.path, f"destination_server.{self.context.name}.path")
        name = p.file or self.context.name
        if "/" in name:
            raise PluginError(f"{self.context.name}.file: a file name without '/', got {name!r} (use `path`)")
        self.file_path = os.path.join(os.path.expanduser(folder), name)
        self.file_mode = parse_mode(str(p.file_mode))
        self.delimiter = p.delimiter or {"csv": ",", "ltsv": "\t"}.get(p.format, "")
        if p.format == "csv" and len(self.delimiter) != 1:
            raise PluginError(f"{self.context.name}.delimiter: csv needs one character, got {p.delimiter!r}")

    def probe(self) -> ProbeResult:
        """The file, or its folder, or the nearest folder that exists (mkdir), writable by this user."""
        if os.path.exists(self.file_path):
            if os.access(self.file_path, os.W_OK):
                return ProbeResult(True, f"{self.file_path} exists and is writable")
            return ProbeResult(False, f"{self.file_path} is not writable", "give this user write access to it")
        folder = os.path.dirname(self.file_path) or "."
        existing = folder
        while not os.path.isdir(existing):
            if not self.params.mkdir or os.path.dirname(existing) == existing:
                break
            existing = os.path.dirname(existing) or "."
        if not os.path.isdir(existing):
            return ProbeResult(False, f"folder {folder} does not exist", "create it, or set mkdir: true")
        if not os.access(existing, os.W_OK | os.X_OK):
            return ProbeResult(
                False, f"{self.file_path} cannot be created: {existing} is not writable", "give this user write access"
            )
        made = "" if existing == folder else f" ({folder} is created)"
        return ProbeResult(True, f"{self.file_path} can be created{made}")

    def on_activate(self) -> None:
        folder = os.path.dirname(self.file_path)
        if self.params.mkdir and not os.path.isdir(folder):
            try:
                make_folders(folder, folder_mode(self.file_mode))
            except OSError as exc:
                # Not fatal: send() retries, and the folder may become writable (a disk mounted late).
                self.context.logger.warning(f"cannot create {folder}: {exc.strerror}; records stay buffered")

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        try:
            fd = self._fd.get()
            fmt = self.params.format
            if fmt == "csv":
                text, rejected = self._render_csv(fd, batch)
            elif fmt in ("json", "plain"):  # the default, a line per record: without a call per line
                text, rejected = "".join([f"{r.to_json()}\n" for r in batch]), {}
            else:
                text, rejected = "".join(self._line(r) for r in batch), {}
            self._append(fd, text.encode())
        except OSError as exc:
            self._fd.close()
            raise RetryableError(f"cannot write {self.file_path}: {exc.strerror or exc}") from exc
        return SendOutcome(reject=rejected) if rejected else None

    def _line(self, record: OutgoingRecord) -> str:
        fmt = self.params.format
        if fmt == "ltsv":
            label = self.params.label_delimiter
            return self.delimiter.join(f"{k}{label}{cell(v)}" for k, v in record.data.items()) + "\n"
        if fmt == "out_file":
            return f"{self.context.name}: [{stamp_text(record.stamp_ns)}, {record.to_json()}]\n"
        if fmt == "template":

            def field(match: re.Match[str]) -> str:
                key = match.group(1)
                if key == "time" and "time" not in record.data:
                    return stamp_text(record.stamp_ns)
                return cell(record.data.get(key))

            return _TEMPLATE_FIELD.sub(field, self.params.template) + "\n"
        return record.to_json() + "\n"

    def _render_csv(self, fd: int, batch: Sequence[OutgoingRecord]) -> tuple[str, dict[int, str]]:
        out = io.StringIO()
        writer = csv.writer(out, delimiter=self.delimiter, lineterminator="\n")
        if self._columns is None:
            self._columns = self._existing_header(fd)
        if self._columns is None and batch:
            self._columns = list(batch[0].data)
            writer.writerow(self._columns)
        columns = self._columns or []
        known = set(columns)
        rejected: dict[int, str] = {}
        for i, record in enumerate(batch):
            extra = [k for k in record.data if k not in known]
            if extra:
                # Writing them would shift or drop columns; the dead-letter store keeps them whole.
                rejected[i] = f"keys not in the csv header of {self.file_path}: {', '.join(extra)}"
                continue
            writer.writerow([cell(record.data.get(c)) for c in columns])
        return out.getvalue(), rejected

    def _existing_header(self, fd: int) -> list[str] | None:
        """Columns of a csv file written before (a restart appends under the same header)."""
        if os.fstat(fd).st_size == 0:
            return None
        with open(self.file_path, newline="", encoding="utf-8") as existing:
            first = existing.readline()
        rows = list(csv.reader([first], delimiter=self.delimiter))
        return rows[0] if rows and rows[0] else None

    # -- file handling -----------------------------------------------------------------------------
    def _open(self) -> int:
        folder = os.path.dirname(self.file_path)
        if self.params.mkdir:
            make_folders(folder, folder_mode(self.file_mode))
        fd, created = _open_append(self.file_path, self.file_mode)
        if created:
            # The new directory entry must be durable too, or a crash can lose the whole file.
            _fsync_dir(folder)
        return fd

    def _same_file(self, fd: int) -> bool:
        """False when the file was moved or deleted (log rotation): then a new one is started."""
        try:
            on_disk = os.stat(self.file_path)
        except FileNotFoundError:
            return False
        opened = os.fstat(fd)
        return (on_disk.st_dev, on_disk.st_ino) == (opened.st_dev, opened.st_ino)

    def _append(self, fd: int, data: bytes) -> None:
        start = os.fstat(fd).st_size
        try:
            view = memoryview(data)
            while view:
                written = os.write(fd, view)
                view = view[written:]
            os.fsync(fd)
        except OSError:
            # Leave no half batch behind (ENOSPC mid-line): the retry writes the whole batch again.
            with contextlib.suppress(OSError):
                os.ftruncate(fd, start)
            raise

    def _close(self, fd: int) -> None:
        self._columns = None
        os.close(fd)


def _open_append(path: str, mode: int) -> tuple[int, bool]:
    """``path`` opened to append, and whether this call created it (then with exactly ``mode``:
    the umask, 077 in DC's processes, would take a group's read away)."""
    flags = os.O_WRONLY | os.O_APPEND | os.O_CLOEXEC
    while True:
        try:
            fd = os.open(path, flags | os.O_CREAT | os.O_EXCL, mode)
        except FileExistsError:
            try:
                return os.open(path, flags), False
            except FileNotFoundError:
                continue  # rotated away between the two opens: create it
        try:
            os.fchmod(fd, mode)
        except OSError:
            os.close(fd)
            raise
        return fd, True


def _fsync_dir(folder: str) -> None:
    try:
        dir_fd = os.open(folder or ".", os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass  # some file systems refuse to fsync a directory; the data itself is synced
    finally:
        os.close(dir_fd)
