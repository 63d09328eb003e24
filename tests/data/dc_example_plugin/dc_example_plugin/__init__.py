"""A measurement from outside DC, registered only by its entry point."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dc_core.measurement import Measurement
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class AnswerParams:
    answer: int = param(42, doc="The answer")


class Answer(Measurement):
    """The answer to everything, from a third-party package."""

    Params = AnswerParams

    def collect(self) -> dict[str, Any] | None:
        return {"answer": self.params.answer}
