"""Reading what is still readable in a damaged buffer file.

SQLite refuses a whole query as soon as it meets one damaged page, so a damaged file read the
ordinary way gives nothing past its first bad page. Here each table is read in ``id`` order and,
where reading fails, the next readable ``id`` is searched for (one ``id`` at a time past the
failure, then in doubling steps, then by bisection back to the first that reads): a damaged leaf
page costs its own rows only. A damaged interior page costs the rows below it, a damaged root
page its whole table; the rows that could not be read are counted, per destination when the
``queues`` table says how many each one had (:class:`SalvageReport`).

SQLite's ``.recover`` (which also reads orphaned pages) is a command of the ``sqlite3`` shell and
its extension, not part of Python's ``sqlite3`` module; this reader needs nothing but the module.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# The destination of rows whose queue could not be named (the ``queues`` table is damaged).
UNKNOWN = "(unknown)"

_FIRST_ID = -(2**63)
_LAST_ID = 2**63 - 1
# Ids probed one by one after a failure before the steps double: a damaged leaf page of small
# records holds a few dozen consecutive ids, which are then skipped without jumping past good ones.
_LINEAR_PROBES = 64


@dataclass
class SalvageReport:
    """What a salvage put back, and what it could not read.

    ``recovered``: rows put back in each destination's queue. ``lost``: rows the damaged file had
    (its ``queues`` table's count) that could not be read, per destination; :data:`UNKNOWN` for
    rows read from a queue whose destination could not be named. ``lost_unknown_count``: True when
    some rows were lost and their number is unknown (the table that counts them is unreadable).
    """

    source: Path
    recovered: dict[str, int] = field(default_factory=dict)
    lost: dict[str, int] = field(default_factory=dict)
    dead_letters_recovered: int = 0
    dead_letters_damaged: bool = False
    lost_unknown_count: bool = False
    damaged_spots: int = 0

    @property
    def recovered_total(self) -> int:
        return sum(self.recovered.values())

    @property
    def lost_total(self) -> int:
        return sum(self.lost.values())

    def summary(self) -> str:
        """One line with the numbers, as the server logs it and ``dc buffer salvage`` prints it."""
        recovered = ", ".join(f"{name} {n}" for name, n in sorted(self.recovered.items()) if n) or "none"
        lost = ", ".join(f"{name} {n}" for name, n in sorted(self.lost.items()) if n)
        text = f"records recovered {self.recovered_total} ({recovered}); lost to the damage {self.lost_total}"
        text += f" ({lost})" if lost else ""
        if self.lost_unknown_count:
            text += " and an unknown number more (its queues table, which counts them, is unreadable)"
        text += f"; dead letters recovered {self.dead_letters_recovered}"
        if self.dead_letters_damaged:
            text += " (some were unreadable)"
        return text


def open_damaged(path: Path) -> sqlite3.Connection:
    """A read-only connection to a (possibly damaged) buffer file, its ``-wal`` included."""
    try:
        conn = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=10.0)
        conn.execute("SELECT 1").fetchall()
    except sqlite3.OperationalError:
        # A read-only connection cannot replay a WAL without its -shm file: open it read-write
        # (the file is a set-aside copy; only its WAL is checkpointed into it).
        conn = sqlite3.connect(path, timeout=10.0)
    return conn


class DamagedReader:
    """The readable rows of each table of a damaged buffer file; counts the damaged spots met."""

    def __init__(self, conn: sqlite3.Connection) -> None:
        self.conn = conn
        self.damaged_spots = 0

    def rows(
        self, table: str, columns: str, where: str = "1", *, after: int | None = None
    ) -> Iterator[tuple[Any, ...]]:
        """``(rowid, *columns)`` of every readable row of ``table`` that matches ``where`` (and whose
        rowid is above ``after``), in rowid order (a queue's ``id`` is its rowid)."""
        query = f"SELECT rowid, {columns} FROM {table} WHERE rowid >= ? AND ({where}) ORDER BY rowid"
        lower: int | None = _FIRST_ID if after is None or after < _FIRST_ID else after + 1
        if lower is not None and lower > _LAST_ID:
            return
        while lower is not None:
            try:
                for row in self.conn.execute(query, (lower,)):
                    lower = int(row[0]) + 1
                    yield row
                return
            except sqlite3.DatabaseError:
                self.damaged_spots += 1
                lower = self._next_readable(query + " LIMIT 1", lower)

    def _readable(self, probe: str, from_id: int) -> bool:
        try:
            self.conn.execute(probe, (from_id,)).fetchall()
        except sqlite3.DatabaseError:
            return False
        return True

    def _next_readable(self, probe: str, failed: int) -> int | None:
        """The smallest id above ``failed`` from which reading works (None: none does)."""
        step, probes = 1, 0
        while True:
            candidate = failed + step
            if candidate > _LAST_ID:
                return None
            if self._readable(probe, candidate):
                break
            failed = candidate
            probes += 1
            if probes >= _LINEAR_PROBES:
                step *= 2
        good = candidate
        while good - failed > 1:  # failed does not read, good does: bisect to the first that reads
            middle = (failed + good) // 2
            if self._readable(probe, middle):
                good = middle
            else:
                failed = middle
        return good

    def tables(self) -> set[str]:
        """The names of the file's tables; empty when its schema cannot be read."""
        try:
            return {str(row[0]) for row in self.conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        except sqlite3.DatabaseError:
            return set()
