"""Rcl destination: each record written to the ROS log of the destination server."""

from __future__ import annotations

from collections.abc import Sequence

from dc_core.destination import Destination, OutgoingRecord, ProbeResult
from dc_core.params import NoParams


class Rcl(Destination[NoParams]):
    """Log each record as JSON through the destination server's ROS logger, at info level."""

    def probe(self) -> ProbeResult:
        return ProbeResult(True, "logs records through the destination server's ROS logger")

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        for record in batch:
            self.context.logger.info(record.to_json())
