"""The condition plugin contract.

A condition answers "is it active now?". Most conditions judge the sample being gated (the
measurement's own JSON, before any metadata is added); some watch their own input (``Moving``
watches odometry) and set ``needs_sample`` to false, which lets the server skip ``collect()``
while they are inactive. With the common ``topic`` parameter a sample-judging condition judges the
latest record of another StringStamped topic instead.

``evaluate`` may raise on missing or malformed data (``KeyError``, ``TypeError``, ``ValueError``,
:class:`dc_core.jsonpath.PathNotFound`): the server treats that as inactive and logs why at debug
level. A condition never takes the server down.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping
from typing import Any, ClassVar

from dc_core.plugin import ParamsT, Plugin, PluginContext

ConditionContext = PluginContext
"""What the measurement server gives a condition plugin (the common plugin context)."""


class Condition(Plugin[ParamsT]):
    """Base class of condition plugins."""

    needs_sample: ClassVar[bool] = True
    # True when the answer depends on earlier samples: such a condition should judge the samples of
    # one measurement only (configuration checks warn when several list it).
    remembers_samples: ClassVar[bool] = False
    # The JSON types (schema names) the value at ``key`` must have for the condition to be active;
    # empty: any. A condition on a field the measurement's schema types otherwise is refused at
    # configure time, for it could never be active.
    value_types: ClassVar[frozenset[str]] = frozenset()

    @abc.abstractmethod
    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        """True when active. ``sample`` is None for conditions with ``needs_sample = False``."""
