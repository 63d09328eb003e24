"""Reading typed JSON values for conditions: numbers as numbers, bools apart, precise reasons.

JSON has one number type; the original split it into float, signed and unsigned and let each
condition accept only one of them. Here an integral value is an integer whatever its spelling
(``3`` or ``3.0``), every number is a double, and a bool is never a number.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from dc_core.jsonpath import get_path
from dc_core.params import param

# The doc of a condition's `key` parameter: the path value_at reads.
KEY_DOC = "Key path, `/`-separated, array items by index"


@dataclass(frozen=True, kw_only=True)
class KeyParams:
    """The parameter of a condition that judges the value at one key path (:func:`value_at`); its own
    parameters follow it."""

    key: str = param(doc=KEY_DOC)


def value_at(sample: Mapping[str, Any] | None, key: str) -> Any:
    """The value at the ``/``-separated ``key``; raises LookupError when there is none."""
    if sample is None:
        raise LookupError("no sample to judge")
    return get_path(sample, key)


def describe(value: Any) -> str:
    """A JSON-ish name and value for error messages (``string "abc"``, ``bool true``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"bool {'true' if value else 'false'}"
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f'string "{shown}"'
    if isinstance(value, (int, float)):
        return f"number {value!r}"
    if isinstance(value, list):
        return f"array of {len(value)}"
    if isinstance(value, Mapping):
        return "object"
    return type(value).__name__


def as_bool(value: Any) -> bool:
    if not isinstance(value, bool):
        raise TypeError(f"not a bool: {describe(value)}")
    return value


def as_number(value: Any) -> int | float:
    """Any JSON number (integer or not); a bool is not a number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"not a number: {describe(value)}")
    return value


def as_integer(value: Any) -> int:
    """A JSON number with no fractional part (``3`` or ``3.0``); ``3.5`` is not an integer."""
    number = as_number(value)
    if isinstance(number, float):
        if not number.is_integer():
            raise TypeError(f"not an integer: {describe(value)}")
        return int(number)
    return number


def as_string(value: Any) -> str:
    if not isinstance(value, str):
        raise TypeError(f"not a string: {describe(value)}")
    return value


def as_list(value: Any, read_item: Callable[[Any], Any]) -> list[Any]:
    """A JSON array whose every item ``read_item`` accepts; the failing index is named."""
    if not isinstance(value, list):
        raise TypeError(f"not an array: {describe(value)}")
    items = []
    for index, item in enumerate(value):
        try:
            items.append(read_item(item))
        except TypeError as exc:
            raise TypeError(f"item {index}: {exc}") from None
    return items
