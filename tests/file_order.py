"""The order in which the suite's files are handed to pytest-xdist's workers: the longest first.

With ``--dist loadfile`` a file runs whole on one worker, and xdist hands out files in collection
order (with ``--no-loadscope-reorder``; its default reorders them by their number of tests, which
put the files of one or two long end-to-end tests last and left three workers idle while the fourth
finished them). Handing out the longest first leaves short files to fill the end.

The seconds per file are measured, not guessed, and kept in ``file_seconds.txt`` beside this
module; regenerate them from a whole run's JUnit report::

    .venv/bin/python -m pytest -n 4 --dist loadfile --no-loadscope-reorder --junitxml=/tmp/run.xml
    .venv/bin/python -m tests.file_order /tmp/run.xml

A file missing from the table (a new one) counts as ``UNKNOWN_S``: the order is a schedule, never a
condition of any test's outcome.
"""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TABLE = Path(__file__).with_name("file_seconds.txt")
UNKNOWN_S = 10.0


def file_seconds() -> dict[str, float]:
    """{path relative to the repository: seconds its tests took in the measured run}."""
    if not TABLE.exists():
        return {}
    table: dict[str, float] = {}
    for line in TABLE.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            seconds, path = line.split(maxsplit=1)
            table[path] = float(seconds)
    return table


def longest_first(paths: list[str], seconds: dict[str, float]) -> list[str]:
    """``paths`` (each once) ordered by their seconds, longest first; ties keep their order."""
    return sorted(dict.fromkeys(paths), key=lambda path: -seconds.get(path, UNKNOWN_S))


def _file_of(classname: str) -> str | None:
    """The test file of a JUnit classname (``tests.test_x`` or ``tests.test_x.TestClass``)."""
    parts = classname.split(".")
    for end in range(len(parts), 0, -1):
        candidate = "/".join(parts[:end]) + ".py"
        if (REPO / candidate).exists():
            return candidate
    return None


def main(report: str) -> None:
    totals: dict[str, float] = {}
    for case in ET.parse(report).getroot().iter("testcase"):
        path = _file_of(case.get("classname", ""))
        if path is not None:
            totals[path] = totals.get(path, 0.0) + float(case.get("time", 0))
    lines = ["# seconds per test file in one whole run (tests/file_order.py says how to regenerate it)"]
    lines += [f"{seconds:.0f} {path}" for path, seconds in sorted(totals.items(), key=lambda item: -item[1])]
    TABLE.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"{len(totals)} files, {sum(totals.values()):.0f} s, written to {TABLE}")


if __name__ == "__main__":
    main(sys.argv[1])
