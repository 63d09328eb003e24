"""Stdout destination: one JSON object per line on the process' standard output."""

from __future__ import annotations

import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RetryableError
from dc_core.params import param

# Every Stdout destination of the process shares the one standard output; a batch must not be
# interleaved with another destination's batch, so the lock is process-wide on purpose.
_STDOUT_LOCK = threading.Lock()

FORMATS = ("json", "json_lines", "json_stream", "plain")


@dataclass(frozen=True, kw_only=True)
class StdoutParams:
    format: str = param(
        "json", choices=FORMATS, doc="Every choice writes one JSON object per line (Fluent Bit's names)"
    )


class Stdout(Destination[StdoutParams]):
    """Print each record as one JSON line on standard output."""

    def probe(self) -> ProbeResult:
        return ProbeResult(True, "prints records on standard output")

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        text = "".join(record.to_json() + "\n" for record in batch)
        with _STDOUT_LOCK:
            try:
                sys.stdout.write(text)
                sys.stdout.flush()
            except (OSError, ValueError) as exc:  # ValueError: stdout closed
                raise RetryableError(f"cannot write to standard output: {exc}") from exc
