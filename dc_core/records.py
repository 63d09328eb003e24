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

orjson parses and writes the common record (~5x faster than ``json`` here, docs/performance.md);
wherever it would accept, refuse or write anything differently, the ``json`` path decides, so both
functions give the same records, texts and reasons as with ``json`` alone.
"""

from __future__ import annotations

import json
import re
from typing import Any

import orjson

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


# orjson reads an integer beyond 64 bits as a float, where json keeps it exact: a text with a run
# of 19 digits (the shortest that can leave the 64-bit range) takes the json path. ASCII digits
# only (no other digit can be part of a JSON number), found as a run of 19 zeros once every digit
# is a zero: bytes.translate and a substring test take 0.2 us where a [0-9]{19} search took 1.2.
_DIGITS_TO_ZERO = bytes.maketrans(b"123456789", b"000000000")
_NINETEEN_ZEROS = b"0" * 19


def _has_long_digit_run(text: str) -> bool:
    return _NINETEEN_ZEROS in text.encode("utf-8", "surrogatepass").translate(_DIGITS_TO_ZERO)


# Where orjson writes a float differently from json: below 1e-4, as 1.5e-9 or 0.00001 where json
# writes 1.5e-09 and 1e-05 (a million random doubles differed nowhere else). Such a text is written
# again by json; so is one with a string that looks alike.
_ORJSON_OWN_FLOAT = re.compile(rb"\de-\d(?!\d)|0\.0000")


def parse_record(text: str) -> dict[str, Any]:
    """The JSON object in ``text``; :class:`MalformedRecord` if it is not one DC can carry on."""
    if not _has_long_digit_run(text):
        try:
            record = orjson.loads(text)
        except orjson.JSONDecodeError:
            pass  # refused, or a NaN, an overflow, a lone surrogate json reads: json says what it is
        else:
            if isinstance(record, dict):
                # Nothing to check: orjson refuses what dump_record would (a number that is not
                # finite, a lone surrogate), and json then gives the reason.
                return record
    return _parse_with_json(text)


def _parse_with_json(text: str) -> dict[str, Any]:
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


def dump_parsed(record: dict[str, Any]) -> str:
    """:func:`dump_record` of a record made only of what :func:`parse_record` returns, and of str,
    bool and finite float values (and lists of them) added to it.

    orjson would write a NaN as ``null`` and a UUID or an Enum as a string, where json refuses them:
    only values of JSON's own types, as a parse gives them, may take this path.
    """
    try:
        encoded = orjson.dumps(record)
    except orjson.JSONEncodeError:  # beyond 64-bit integers, nesting deeper than orjson writes
        return dump_record(record)
    # Both substrings are in every text the pattern matches; most texts have neither, and a
    # substring test costs a quarter of the search.
    if (b"e-" in encoded or b"0.0000" in encoded) and _ORJSON_OWN_FLOAT.search(encoded) is not None:
        return dump_record(record)
    return encoded.decode()


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


def measurement_of(topic: str) -> str:
    """The measurement a record's topic names: its last segment (``/dc/measurement/camera``: camera;
    "" for ``/``). One rule for every server and plugin that names a record by its topic. A trailing
    ``/`` is passed over: no ROS name has one, but a topic from elsewhere (a NATS header) may."""
    return topic.rstrip("/").rsplit("/", 1)[-1]
