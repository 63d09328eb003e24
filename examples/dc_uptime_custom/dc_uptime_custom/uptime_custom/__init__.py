"""UptimeCustom: DC's Uptime with a schema of its own and a failed-validation hook."""

from __future__ import annotations

from typing import Any

from dc_core.measurement import MeasurementContext
from dc_core.params import NoParams
from dc_measurements.uptime import Uptime


class UptimeCustom(Uptime):
    """Uptime checked against a schema every record fails, to show the failed-validation hook."""

    # collect() and the (absent) parameters are Uptime's. The schema is looked up beside the module
    # that defines the class, so this subclass brings its own schema.json.

    def __init__(self, context: MeasurementContext, params: NoParams) -> None:
        super().__init__(context, params)
        self._failed_validations = 0

    def on_failed_validation(self, record: dict[str, Any], error: str) -> None:
        # DC has logged the validation error already; this is where a plugin reacts to it (count
        # it, raise an alarm, switch to a fallback). Here: say so, and count it.
        self._failed_validations += 1
        self.context.logger.info(
            f"on_failed_validation called for time={record.get('time')} ({self._failed_validations} so far)"
        )

    def counters(self) -> dict[str, int]:
        return {**super().counters(), "failed_validations": self._failed_validations}
