"""Double* and Integer* conditions: compare the number at a key path with a configured number.

Numbers compare as numbers: an integer JSON value works with the Double conditions and an
integral float (``3.0``) with the Integer ones. A non-integral value (``3.5``) is not an
integer, so the Integer conditions are inactive on it rather than rounding it. Bools are not
numbers.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

from dc_conditions.compare import KeyParams, as_integer, as_number, value_at
from dc_core.condition import Condition
from dc_core.params import param

_INCLUDE_DOC = "Whether a value equal to `value` counts (<= / >= rather than < / >)"

Relation = Literal["equal", "below", "above"]


@dataclass(frozen=True, kw_only=True)
class DoubleEqualParams(KeyParams):
    value: float = param(doc="Number the value must equal (exact comparison)")


@dataclass(frozen=True, kw_only=True)
class DoubleBoundParams(KeyParams):
    value: float = param(doc="Bound the value is compared with")
    include_value: bool = param(True, doc=_INCLUDE_DOC)


@dataclass(frozen=True, kw_only=True)
class IntegerEqualParams(KeyParams):
    value: int = param(doc="Integer the value must equal")


@dataclass(frozen=True, kw_only=True)
class IntegerBoundParams(KeyParams):
    value: int = param(doc="Bound the value is compared with")
    include_value: bool = param(True, doc=_INCLUDE_DOC)


class _NumericCondition(Condition[Any]):
    relation: ClassVar[Relation] = "equal"
    integers_only: ClassVar[bool] = False
    # An "integer" field is a number; a "number" one may hold 3.0, which the Integer conditions take.
    value_types = frozenset({"number", "integer"})

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        raw = value_at(sample, self.params.key)
        actual = as_integer(raw) if self.integers_only else as_number(raw)
        bound: int | float = self.params.value
        if self.relation == "equal":
            return actual == bound
        inclusive: bool = self.params.include_value
        if self.relation == "below":
            return actual <= bound if inclusive else actual < bound
        return actual >= bound if inclusive else actual > bound


class DoubleEqual(_NumericCondition):
    """Number at the key path equals `value` (integers accepted)."""

    Params = DoubleEqualParams


class DoubleInferior(_NumericCondition):
    """Number at the key path is below `value` (or equal, with `include_value`)."""

    Params = DoubleBoundParams
    relation = "below"


class DoubleSuperior(_NumericCondition):
    """Number at the key path is above `value` (or equal, with `include_value`)."""

    Params = DoubleBoundParams
    relation = "above"


class IntegerEqual(_NumericCondition):
    """Integer at the key path equals `value` (3.0 counts as 3; 3.5 is not an integer)."""

    Params = IntegerEqualParams
    integers_only = True


class IntegerInferior(_NumericCondition):
    """Integer at the key path is below `value` (or equal, with `include_value`)."""

    Params = IntegerBoundParams
    relation = "below"
    integers_only = True


class IntegerSuperior(_NumericCondition):
    """Integer at the key path is above `value` (or equal, with `include_value`)."""

    Params = IntegerBoundParams
    relation = "above"
    integers_only = True
