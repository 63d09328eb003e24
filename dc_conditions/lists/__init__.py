"""List* conditions: the JSON array at a key path equals the configured list.

With ``order_matters: false`` the comparison is between multisets: the same items the same
number of times, in any order (``[1, 1, 2]`` differs from ``[1, 2, 2]``). Items are typed like
the scalar conditions: numbers as numbers, bools apart.
"""

from __future__ import annotations

import abc
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dc_conditions.compare import as_bool, as_integer, as_list, as_number, as_string, value_at
from dc_core.condition import Condition
from dc_core.params import param

_KEY_DOC = "Key path of the array, `/`-separated, array items by index"
_ORDER_DOC = "Compare item by item (true) or as multisets, in any order (false)"


@dataclass(frozen=True, kw_only=True)
class _ArrayKeyParams:
    key: str = param(doc=_KEY_DOC)


@dataclass(frozen=True, kw_only=True)
class ListBoolEqualParams(_ArrayKeyParams):
    value: list[bool] = param(doc="Expected bools")
    order_matters: bool = param(True, doc=_ORDER_DOC)


@dataclass(frozen=True, kw_only=True)
class ListDoubleEqualParams(_ArrayKeyParams):
    value: list[float] = param(doc="Expected numbers (exact comparison)")
    order_matters: bool = param(True, doc=_ORDER_DOC)


@dataclass(frozen=True, kw_only=True)
class ListIntegerEqualParams(_ArrayKeyParams):
    value: list[int] = param(doc="Expected integers")
    order_matters: bool = param(True, doc=_ORDER_DOC)


@dataclass(frozen=True, kw_only=True)
class ListStringEqualParams(_ArrayKeyParams):
    value: list[str] = param(doc="Expected strings")
    order_matters: bool = param(True, doc=_ORDER_DOC)


class _ListEqual(Condition[Any]):
    value_types = frozenset({"array"})

    @staticmethod
    @abc.abstractmethod
    def read_item(item: Any, /) -> Any:
        """The item as its Python value; raises TypeError when it has the wrong JSON type.

        Each list condition sets it to one of dc_conditions.compare's readers (positional-only, as
        they name their argument ``value``), so that its items are typed as the scalar conditions'
        values are."""

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        actual = as_list(value_at(sample, self.params.key), self.read_item)
        expected: list[Any] = self.params.value
        if self.params.order_matters:
            return actual == expected
        return Counter(actual) == Counter(expected)


class ListBoolEqual(_ListEqual):
    """Array of bools at the key path equals `value`, in order or as a multiset."""

    Params = ListBoolEqualParams
    read_item = staticmethod(as_bool)


class ListDoubleEqual(_ListEqual):
    """Array of numbers at the key path equals `value`, in order or as a multiset."""

    Params = ListDoubleEqualParams
    read_item = staticmethod(as_number)


class ListIntegerEqual(_ListEqual):
    """Array of integers at the key path equals `value`, in order or as a multiset."""

    Params = ListIntegerEqualParams
    read_item = staticmethod(as_integer)


class ListStringEqual(_ListEqual):
    """Array of strings at the key path equals `value`, in order or as a multiset."""

    Params = ListStringEqualParams
    read_item = staticmethod(as_string)
