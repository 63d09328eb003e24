"""Where each hand-off publisher got to, kept on disk so that its death is counted (docs/delivery.md, "The hand-off").

measurement_server and group_server hold what they publish until destination_server acknowledges
it (dc_core.handoff). A process killed with -9 loses what it held, and its successor, with a new
publisher id, knew nothing of it: its own records (timer samples, group outputs) were lost without
a count. So each hand-off publisher (one per output topic) keeps a small file, ``<id>.mark`` in
``<data home>/dc/handoff/domain-<D>/<namespace>/<node name>/`` (dc_core.paths.instance_dir), that
says the highest number it published, written before the record is published, the highest number
destination_server acknowledged, and whether its records forward a source's numbers (a
StringStamped measurement's, whose losses destination_server counts from those already). The file
is written through a shared memory map (~0.4 us a record, no system call; the page cache keeps it
whatever becomes of the process, a power cut may not) and locked (flock) while its publisher lives.

At its next start the server takes the files no live process locks and announces them on
:data:`ENDED_TOPIC` (transient local: a destination_server that starts later gets them too):
"publisher W on topic T ended at number H, acknowledged up to A". destination_server counts the
numbers up to H it never handled as ``missing``, commits that it did so (a restart of it does not
count them again) and acknowledges H; the announcing server then deletes the file. A file whose
records were all acknowledged is deleted at once, and so is one that forwards a source's numbers;
at most :data:`MAX_ENDED` wait, the oldest beyond are deleted with a warning.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import mmap
import os
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dc_core.paths import instance_dir
from dc_core.private_files import create_private, make_folders

ENDED_TOPIC = "dc/handoff_ended"
"""Relative, as the acks: the publishers of this namespace that ended holding unacknowledged records."""
SUFFIX = ".mark"
NEW_SUFFIX = ".new"
MAGIC = b"DCW1"
# magic, then the highest number published, the highest acknowledged, and 1 when the records forward
# a source's numbers; the topic follows, in UTF-8.
HEADER = struct.Struct("<4s4xQQB7x")
HIGH_AT, ACKED_AT, FORWARDING_AT = 8, 16, 24
NUMBER = struct.Struct("<Q")
MAX_ENDED = 64
"""Files of ended publishers kept per server: a destination_server that never comes back cannot make them pile up."""


def marks_folder(namespace: str, node_name: str) -> Path:
    return instance_dir("handoff", namespace) / node_name


@dataclass(frozen=True)
class Ended:
    """A publisher that ended holding records not acknowledged."""

    topic: str
    writer: int
    high: int  # the highest number it published (it may not have been sent: written first)
    acked: int  # the highest number destination_server acknowledged to it


class WriterMark:
    """The file of one living publisher: created, locked and mapped; ``map`` is written at :data:`HIGH_AT`."""

    def __init__(self, folder: Path, writer: int, topic: str) -> None:
        make_folders(folder)
        self.path = folder / f"{writer:x}{SUFFIX}"
        encoded = topic.encode()
        # Written and locked under another name, then renamed: a starting server never takes a mark
        # that is still being made for an ended one.
        making = self.path.with_name(self.path.name + NEW_SUFFIX)
        self._fd = create_private(making, os.O_RDWR)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.ftruncate(self._fd, 0)
            os.write(self._fd, HEADER.pack(MAGIC, 0, 0, 0) + encoded)
            self.map = mmap.mmap(self._fd, HEADER.size + len(encoded))
            os.rename(making, self.path)
        except BaseException:
            os.close(self._fd)
            with contextlib.suppress(OSError):
                making.unlink()
            raise
        self.forwarding = False

    def acked(self, floor: int) -> None:
        NUMBER.pack_into(self.map, ACKED_AT, floor)

    def forwards(self) -> None:
        self.forwarding = True
        self.map[FORWARDING_AT] = 1

    def close(self, keep: bool) -> None:
        """Unmap and unlock; ``keep`` the file when records are held, for the next start to announce."""
        if not keep:
            with contextlib.suppress(OSError):
                self.path.unlink()
        self.map.close()
        os.close(self._fd)


def _read(fd: int) -> tuple[str, int, int, bool] | None:
    data = os.pread(fd, 64 * 1024, 0)
    if len(data) < HEADER.size:
        return None
    magic, high, acked, forwarding = HEADER.unpack_from(data)
    if magic != MAGIC:
        return None
    try:
        return data[HEADER.size :].decode(), high, acked, bool(forwarding)
    except UnicodeDecodeError:
        return None


class EndedWriters:
    """The files of the ended publishers of one server, locked by this process until retired or released."""

    def __init__(self, folder: Path, warn: Callable[[str], None]) -> None:
        self.folder = folder
        self._held: dict[tuple[str, int], tuple[Ended, int, Path]] = {}
        self._warn = warn

    def scan(self) -> list[Ended]:
        """Take the files of publishers that ended (their process is gone: the lock is free)."""
        found: list[tuple[float, Ended, int, Path]] = []
        with contextlib.suppress(FileNotFoundError):
            for path in self.folder.iterdir():
                taken = self._take(path)
                if taken is not None:
                    found.append(taken)
        found.sort(key=lambda one: one[0])
        for _, ended, fd, path in found[: max(0, len(found) - MAX_ENDED)]:
            self._warn(
                f"{ended.topic}: publisher {ended.writer:x} ended holding up to {ended.high - ended.acked} records not "
                f"acknowledged; more than {MAX_ENDED} such publishers wait for destination_server, the oldest are "
                f"forgotten uncounted ({path} deleted)"
            )
            self._delete(fd, path)
        for _, ended, fd, path in found[-MAX_ENDED:] if found else []:
            self._held[(ended.topic, ended.writer)] = (ended, fd, path)
        return self.ended()

    def _take(self, path: Path) -> tuple[float, Ended, int, Path] | None:
        if path.name.endswith(SUFFIX + NEW_SUFFIX):
            self._forget_unfinished(path)
            return None
        if not path.name.endswith(SUFFIX):
            return None
        try:
            writer = int(path.name[: -len(SUFFIX)], 16)
            fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
        except (ValueError, OSError):
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            info = os.fstat(fd)
            content = _read(fd) if info.st_nlink else None  # unlinked meanwhile: retired by its publisher
        except OSError:
            os.close(fd)
            return None
        if content is None or writer <= 0:
            if info.st_nlink:
                self._warn(f"{path}: not a hand-off mark, deleted")
            self._delete(fd, path if info.st_nlink else None)
            return None
        topic, high, acked, forwarding = content
        if high <= acked or forwarding:
            # Everything acknowledged, or counted by destination_server from the source's numbers.
            self._delete(fd, path)
            return None
        return info.st_mtime, Ended(topic, writer, high, acked), fd, path

    def _forget_unfinished(self, path: Path) -> None:
        """A mark its process died making (nothing published yet), unless it is being made now."""
        try:
            fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
        except OSError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            return
        self._delete(fd, path)

    @staticmethod
    def _delete(fd: int, path: Path | None) -> None:
        if path is not None:
            with contextlib.suppress(OSError):
                path.unlink()
        os.close(fd)

    def ended(self) -> list[Ended]:
        return [ended for ended, _, _ in self._held.values()]

    def retire(self, acks: Mapping[tuple[str, int], int]) -> list[Ended]:
        """Delete the files of the publishers destination_server acknowledged to their end; returns them."""
        retired = []
        for key, (ended, fd, path) in list(self._held.items()):
            if acks.get(key, -1) >= ended.high:
                del self._held[key]
                self._delete(fd, path)
                retired.append(ended)
        return retired

    def release(self) -> None:
        """Unlock what is not retired: the next start announces it again."""
        for _, fd, _ in self._held.values():
            os.close(fd)
        self._held.clear()


def ended_document(server: str, ended: list[Ended]) -> str:
    return json.dumps({"server": server, "ended": [[e.topic, f"{e.writer:x}", e.high, e.acked] for e in ended]})


def parse_ended(text: str) -> tuple[str, list[Ended]] | None:
    """The server and the publishers an :data:`ENDED_TOPIC` message names; None for anything else."""
    try:
        document = json.loads(text)
        parsed = [Ended(str(t), int(w, 16), int(h), int(a)) for t, w, h, a in document["ended"]]
        server = str(document["server"])
    except (ValueError, TypeError, KeyError, AttributeError):
        return None
    return server, [e for e in parsed if e.writer > 0 and e.high > 0 and e.acked >= 0]


def ended_qos(depth: int = 1) -> Any:
    """Transient local, the last message of each server: a destination_server that starts later gets it
    (its subscription is deeper: one message from each server). The records' profile, of another depth."""
    from dc_core.qos import record_qos

    return record_qos(depth)
