"""Names made from a record: an MQTT topic or a NATS subject from a template over the record's keys.

``"dc.{robot_name}.{name}"`` names the record's top-level keys; what the template may not hold
(MQTT's wildcards, NATS' separators) is the caller's to say. One parser and one filling for every
destination that routes by the record, so that a template is read, and refused, the same way.
"""

from __future__ import annotations

import string
from collections.abc import Mapping
from typing import Any


def template_keys(template: str, *, forbidden: str = "", forbidden_problem: str = "") -> list[str]:
    """The record keys a template names (``"dc/{robot}/{name}"`` → robot, name).

    Raises ValueError with what was expected: a positional ``{}``, a conversion or format spec, an
    attribute or index (``{a.b}``, ``{a[0]}``), an unbalanced brace, or one of the characters of
    ``forbidden`` in the template's text (``forbidden_problem`` says what was expected then).
    """
    keys: list[str] = []
    for literal, field, spec, conversion in string.Formatter().parse(template):
        if forbidden and any(c in literal for c in forbidden):
            raise ValueError(forbidden_problem)
        if field is None:
            continue
        if not field or field.isdigit():
            raise ValueError("placeholders that name a record key, like {name}")
        if spec or conversion or any(c in field for c in ".["):
            raise ValueError(f"plain placeholders like {{name}}, got {{{field}...}}")
        keys.append(field)
    return keys


def fill_template(template: str, keys: list[str], data: Mapping[str, Any], what: str) -> str:
    """``template`` with each of ``keys`` replaced by the record's value; ValueError saying why it cannot be.

    ``what`` names the result in the messages ("topic", "subject").
    """
    values: dict[str, str] = {}
    for key in keys:
        if key not in data:
            raise ValueError(f"the record has no {key!r} for the {what} template {template!r}")
        values[key] = _text(key, data[key], what)
    return template.format_map(values)


def _text(key: str, value: Any, what: str) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (str, int, float)):
        return str(value)
    kind = "null" if value is None else type(value).__name__
    raise ValueError(f"the record's {key!r} is {kind}, not text or a number, so it cannot go in a {what}")
