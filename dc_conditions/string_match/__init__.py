"""StringMatch: the string at a key path fully matches a regular expression."""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dc_conditions.compare import KeyParams, as_string, value_at
from dc_core.condition import Condition, ConditionContext
from dc_core.errors import PluginError
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class StringMatchParams(KeyParams):
    regex: str = param(doc="Python regular expression the whole string must match")


class StringMatch(Condition[StringMatchParams]):
    """String at the key path fully matches `regex` (a non-string value is inactive)."""

    value_types = frozenset({"string"})

    def __init__(self, context: ConditionContext, params: StringMatchParams) -> None:
        super().__init__(context, params)
        self._pattern: re.Pattern[str] | None = None

    def on_configure(self) -> None:
        try:
            self._pattern = re.compile(self.params.regex)
        except re.error as exc:
            raise PluginError(
                f"{self.context.name}.regex: invalid regular expression {self.params.regex!r}: {exc}"
            ) from None

    def on_cleanup(self) -> None:
        self._pattern = None

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        if self._pattern is None:
            raise ValueError("not configured")
        text = as_string(value_at(sample, self.params.key))
        return self._pattern.fullmatch(text) is not None
