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
from typing import Any, ClassVar, Protocol

from dc_core.logs import Logger
from dc_core.params import NoParams


class ConditionContext(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def logger(self) -> Logger: ...
    @property
    def node(self) -> Any:
        """The rclpy node, for conditions with their own subscriptions (``None`` without ROS)."""


class Condition(abc.ABC):
    """Base class of condition plugins."""

    Params: ClassVar[type] = NoParams
    needs_sample: ClassVar[bool] = True
    # True when the answer depends on earlier samples: such a condition should judge the samples of
    # one measurement only (configuration checks warn when several list it).
    remembers_samples: ClassVar[bool] = False

    def __init__(self, context: ConditionContext, params: Any) -> None:
        self.context = context
        self.params = params

    def on_configure(self) -> None:
        """Create subscriptions; raise PluginError to fail configure."""

    def on_activate(self) -> None:
        """Called when the server activates."""

    def on_deactivate(self) -> None:
        """Called when the server deactivates."""

    def on_cleanup(self) -> None:
        """Release what on_configure created."""

    @abc.abstractmethod
    def evaluate(self, sample: Mapping[str, Any] | None) -> bool:
        """True when active. ``sample`` is None for conditions with ``needs_sample = False``."""
