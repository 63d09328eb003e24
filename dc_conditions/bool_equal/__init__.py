"""BoolEqual: a JSON bool equals the configured bool."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dc_conditions.compare import KeyParams, as_bool, value_at
from dc_core.condition import Condition
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class BoolEqualParams(KeyParams):
    value: bool = param(doc="Expected bool")


class BoolEqual(Condition[BoolEqualParams]):
    """Bool at the key path equals `value` (a number or string is not a bool: inactive)."""

    value_types = frozenset({"boolean"})

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        params: BoolEqualParams = self.params
        return as_bool(value_at(sample, params.key)) == params.value
