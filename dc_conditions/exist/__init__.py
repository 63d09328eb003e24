"""Exist: the key path is present in the sample."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dc_core.condition import Condition
from dc_core.jsonpath import has_path
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class ExistParams:
    key: str = param(doc="Key path, `/`-separated, array items by index (`inspected/barcode/0`)")


class Exist(Condition[ExistParams]):
    """Key path exists in the sample, whatever its value (null, empty and false included)."""

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        if sample is None:
            raise LookupError("no sample to judge")
        params: ExistParams = self.params
        return has_path(sample, params.key)
