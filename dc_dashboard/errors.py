"""The dashboard's one error root: whatever a page cannot show, said in a sentence, never as a traceback."""

from __future__ import annotations

from dc_core.errors import DcError


class DashboardError(DcError):
    """A source (PostgreSQL, S3, a metrics URL) could not give what a page needs; the message says which."""


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (PostgreSQL's carry a multi-line detail), or its type."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
