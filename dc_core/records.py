"""JSON records as DC reads and writes them: one rule for every server's intake and output.

A record is a JSON object whose text every other tool can read back. Python's ``json`` module
accepts more than that, and each extra was a record that broke delivery or someone's parser:

- ``NaN``, ``Infinity`` and ``-Infinity`` are not JSON (RFC 8259), and a number too large for a
  double (``1e400``) reads as infinity: written back out, either is ``NaN``/``Infinity`` text that
  other tools reject;
- an escaped lone surrogate (``"\\udcff"``) reads as a string that cannot be encoded as UTF-8: the
  buffer could not store it, and rclpy cannot publish it;
- nesting deeper than the parser's recursion limit raises ``RecursionError``, not ``ValueError``.

:func:`parse_record` returns only records that :func:`dump_record` can write out again, and both
raise :class:`MalformedRecord` with a reason, so a server counts the record as malformed and goes on.
"""

from __future__ import annotations

import json
import re
from typing import Any

from dc_core.errors import DcError


class MalformedRecord(DcError):
    """A text that is not a record DC can carry; the message says why."""


def _reject_constant(name: str) -> Any:
    raise MalformedRecord(f"{name} is not a JSON number (non-finite numbers are not carried)")


# One decoder, built once: json.loads(text, parse_constant=...) would build a new one per call.
_DECODER = json.JSONDecoder(parse_constant=_reject_constant)
# What a text must hold for its parsed record to fail dump_record: a \u escape (a lone surrogate
# can come only from one) or a number that may overflow a double (a 3-digit exponent, or 309+
# digits). Most records hold neither and are not serialised twice. Three cheap tests rather than
# one regex: the alternation cost 2 us a record, these 0.9.
_BIG_EXPONENT = re.compile(r"[eE][+]?\d{3}")
_LONG_NUMBER = re.compile(r"\d{309}")


def _may_not_dump(text: str) -> bool:
    return (
        "\\u" in text
        or _BIG_EXPONENT.search(text) is not None
        or (len(text) > 309 and _LONG_NUMBER.search(text) is not None)
    )


def parse_record(text: str) -> dict[str, Any]:
    """The JSON object in ``text``; :class:`MalformedRecord` if it is not one DC can carry on."""
    try:
        record = _DECODER.decode(text)
    except MalformedRecord:
        raise
    except ValueError as exc:  # JSONDecodeError, and an integer longer than Python converts (4,300 digits)
        raise MalformedRecord(f"invalid JSON ({exc})") from None
    except RecursionError:
        raise MalformedRecord("nested too deeply for the JSON parser") from None
    if not isinstance(record, dict):
        raise MalformedRecord(f"expected a JSON object, got a JSON {_json_kind(record)}")
    if _may_not_dump(text):
        dump_record(record)
    return record


def dump_record(record: Any) -> str:
    """Compact JSON text of ``record``; :class:`MalformedRecord` if it would not be valid UTF-8 JSON."""
    try:
        text = json.dumps(record, ensure_ascii=False, separators=(",", ":"), allow_nan=False)
    except ValueError as exc:
        if "Out of range float" in str(exc):
            raise MalformedRecord("a number is not finite (NaN or Infinity, or too large for a double)") from None
        raise MalformedRecord(f"cannot be written as JSON: {exc}") from None
    except RecursionError:
        raise MalformedRecord("nested too deeply for the JSON encoder") from None
    except TypeError as exc:
        raise MalformedRecord(f"not JSON-serialisable: {exc}") from None
    if not text.isascii():  # O(1) in CPython: the string knows it is ASCII
        try:
            text.encode("utf-8")
        except UnicodeEncodeError as exc:
            bad = text[exc.start : exc.end].encode("utf-8", "backslashreplace").decode("ascii")
            raise MalformedRecord(f"a string holds a lone surrogate {bad}, which is not Unicode text") from None
    return text


def _json_kind(value: Any) -> str:
    if isinstance(value, list):
        return "array"
    if isinstance(value, str):
        return "string"
    if isinstance(value, bool):
        return "boolean"
    if value is None:
        return "null"
    return "number"
