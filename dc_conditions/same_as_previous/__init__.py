"""SameAsPrevious: the sample carries the same data as the previous one.

The comparison covers the whole sample except the ``tags`` key and the key paths matched by
``exclude``. The values at ``keys`` are file paths: their files' contents are compared (a
SHA-256 of the whole file), not their names, so a new file with the same content is the same
and a file rewritten in place is not.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dc_conditions.compare import as_string, value_at
from dc_core.condition import Condition, ConditionContext
from dc_core.errors import PluginError
from dc_core.jsonpath import flatten
from dc_core.params import param

_CHUNK = 1 << 20

Fingerprint = tuple[dict[str, tuple[str, Any]], dict[str, str]]


@dataclass(frozen=True, kw_only=True)
class SameAsPreviousParams:
    # param() copies list defaults, which ruff cannot see (RUF009)
    keys: list[str] = param(
        [], doc="Key paths whose values are file paths: the files' contents are compared, not the paths"
    )
    exclude: list[str] = param(
        [], doc="Regular expressions over `/`-joined key paths (`cameras/0/stamp`) left out of the comparison"
    )


def file_digest(path: str) -> str:
    """SHA-256 of a whole file; raises LookupError when it cannot be read."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as stream:
            while chunk := stream.read(_CHUNK):
                digest.update(chunk)
    except OSError as exc:
        raise LookupError(f"cannot read file {path!r}: {exc.strerror or exc}") from None
    return digest.hexdigest()


def _ancestors(path: str) -> list[str]:
    """``a/b/0`` → ``["a", "a/b", "a/b/0"]``: excluding a key excludes what is under it."""
    parts = path.split("/")
    return ["/".join(parts[: i + 1]) for i in range(len(parts))]


def _canonical_path(document: Any, key: str) -> str:
    """``key`` as ``flatten`` spells it: no outer slashes, negative array indices resolved."""
    parts = []
    node = document
    for part in (p for p in key.split("/") if p):
        if isinstance(node, list):
            index = int(part) % len(node)
            parts.append(str(index))
            node = node[index]
        else:
            parts.append(part)
            node = node[part]
    return "/".join(parts)


def _typed(value: Any) -> tuple[str, Any]:
    """A leaf with its JSON kind, so that ``true`` never equals ``1`` (Python says it does)."""
    if isinstance(value, bool):
        return "bool", value
    if isinstance(value, (int, float)):
        return "number", value
    return type(value).__name__, value


class SameAsPrevious(Condition[SameAsPreviousParams]):
    """Sample equals the previous one, ignoring `tags` and `exclude`, comparing the files at `keys`."""

    remembers_samples = True

    def __init__(self, context: ConditionContext, params: SameAsPreviousParams) -> None:
        super().__init__(context, params)
        self._exclude: list[re.Pattern[str]] = []
        self._previous: Fingerprint | None = None

    def on_configure(self) -> None:
        patterns = []
        for index, text in enumerate(self.params.exclude):
            try:
                patterns.append(re.compile(text))
            except re.error as exc:
                raise PluginError(
                    f"{self.context.name}.exclude[{index}]: invalid regular expression {text!r}: {exc}"
                ) from None
        self._exclude = patterns
        self._previous = None

    def on_cleanup(self) -> None:
        self._previous = None

    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        current = self.fingerprint(sample)
        previous, self._previous = self._previous, current
        return previous is not None and previous == current

    def fingerprint(self, sample: Mapping[str, Any] | None) -> Fingerprint:
        """What is compared: the kept leaves by key path, and the file digests by key."""
        if sample is None:
            raise LookupError("no sample to judge")
        digests: dict[str, str] = {}
        for key in self.params.keys:
            file_path = as_string(value_at(sample, key))  # first: says precisely what is missing
            digests[_canonical_path(sample, key)] = file_digest(file_path)
        leaves: dict[str, tuple[str, Any]] = {}
        for slashed, value in flatten({k: v for k, v in sample.items() if k != "tags"}).items():
            path = slashed[1:]
            if path not in digests and not self._excluded(path):
                leaves[path] = _typed(value)
        return leaves, digests

    def _excluded(self, path: str) -> bool:
        return any(p.fullmatch(prefix) for p in self._exclude for prefix in _ancestors(path))
