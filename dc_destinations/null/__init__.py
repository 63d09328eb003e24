"""Null destination: accepts and discards every record."""

from __future__ import annotations

from collections.abc import Sequence

from dc_core.destination import Destination, OutgoingRecord, ProbeResult
from dc_core.params import NoParams


class Null(Destination[NoParams]):
    """Discard every record (confirmed at once): for tests and for measuring the pipeline alone."""

    def probe(self) -> ProbeResult:
        return ProbeResult(True, "discards every record")

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        return None
