"""Damage to a buffer file at rest, as a failing disk would do it: what the salvage tests share."""

from __future__ import annotations

from pathlib import Path


def damage_pages(path: Path, count: int = 10, page_size: int = 4096) -> list[int]:
    """Overwrite ``count`` pages spread evenly over the file with garbage (1-based page numbers).

    Never page 1 nor the first pages after it, where SQLite put the schema and each table's root:
    a damaged root costs its whole table (counted, see dc_destinations.salvage); here the damage
    falls on the records' pages, as it mostly would on a large buffer.
    """
    pages = path.stat().st_size // page_size
    chosen = [pages * (i + 1) // (count + 1) + 1 for i in range(count)]
    assert min(chosen) > 16 and len(set(chosen)) == count, chosen
    with path.open("r+b") as handle:
        for page in chosen:
            handle.seek((page - 1) * page_size)
            handle.write(bytes((page * 7 + i * 31) % 256 for i in range(page_size)))
    return chosen
