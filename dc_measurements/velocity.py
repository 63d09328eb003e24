"""What CmdVel and Speed share: the latest twist of a topic, and what a poll reports of it.

A poll reports the newest message received since the previous poll. When none arrived, it reports
nothing by default, as the original did (a robot standing without a controller sends no
``/cmd_vel``); with ``repeat_last: true`` it reports the last message again, and the record's
``age`` says how old that message is. Either way the state is not cleared by a poll of another
measurement or by a failed publication: each measurement keeps its own.
"""

from __future__ import annotations

import abc
import math
import threading
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, TypeVar

from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param
from dc_core.qos import SENSOR_QOS
from dc_core.rostime import now_ns


def repeat_last_param() -> Any:
    return param(
        False,
        doc="false: a poll with no new message since the previous one publishes nothing; true: it publishes the "
        "last message again, with its `age`",
    )


def vector(v: Any) -> dict[str, float]:
    return {"x": float(v.x), "y": float(v.y), "z": float(v.z)}


def twist_record(twist: Any, age_s: float) -> dict[str, Any]:
    """The record of a geometry_msgs/Twist: both vectors, the planar speed, and how old it is."""
    return {
        "linear": vector(twist.linear),
        "angular": vector(twist.angular),
        "computed": math.hypot(float(twist.linear.x), float(twist.linear.y)),
        "age": max(0.0, age_s),
    }


@dataclass
class _Received:
    twist: Any
    received_ns: int
    stamp_ns: int | None  # the message's header stamp, when it has one


class LatestTwist:
    """The newest twist received and whether a poll has reported it yet (callbacks and polls may run on
    different threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latest: _Received | None = None
        self._reported = True
        self.received = 0

    def update(self, twist: Any, received_ns: int, stamp_ns: int | None = None) -> None:
        with self._lock:
            self._latest = _Received(twist, received_ns, stamp_ns)
            self._reported = False
            self.received += 1

    def take(self, now_ns: int, repeat_last: bool) -> dict[str, Any] | None:
        """The record a poll at ``now_ns`` reports, or None (see the module documentation)."""
        return self.take_stamped(now_ns, repeat_last)[0]

    def take_stamped(self, now_ns: int, repeat_last: bool) -> tuple[dict[str, Any] | None, int | None]:
        """:meth:`take`, and the stamp of the message when it is reported for the first time (else None)."""
        with self._lock:
            latest = self._latest
            if latest is None or (self._reported and not repeat_last):
                return None, None
            fresh = not self._reported
            self._reported = True
        # A message repeated (repeat_last) is dated by the poll: its `age` says how old it is.
        return twist_record(latest.twist, (now_ns - latest.received_ns) / 1e9), latest.stamp_ns if fresh else None

    def reset(self) -> None:
        with self._lock:
            self._latest = None
            self._reported = True


class TwistParams(Protocol):
    @property
    def repeat_last(self) -> bool: ...


TwistParamsT = TypeVar("TwistParamsT", bound=TwistParams)


class LatestTwistMeasurement(Measurement[TwistParamsT]):
    """A measurement that reports the newest twist of one topic (CmdVel, Speed): see the module documentation."""

    message_type: ClassVar[Any]

    def __init__(self, context: MeasurementContext, params: TwistParamsT) -> None:
        super().__init__(context, params)
        self._latest = LatestTwist()
        self._subscription: Any = None

    @property
    @abc.abstractmethod
    def topic(self) -> str:
        """The topic of ``message_type`` subscribed to."""

    @staticmethod
    def twist_of(message: Any) -> Any:
        """The geometry_msgs/Twist a message carries."""
        return message

    @staticmethod
    def stamp_of(message: Any) -> int | None:
        """The time the message describes (its header stamp), if it has one: the record is dated with it."""
        return None

    def on_configure(self) -> None:
        self.on_cleanup()
        self.subscribe(self.message_type)

    def subscribe(self, message_type: Any) -> None:
        """Subscribe to ``topic`` as ``message_type``, in place of the current subscription."""
        self._unsubscribe()
        self._subscription = self.context.subscribe(message_type, self.topic, self._on_message, SENSOR_QOS)

    def _unsubscribe(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None

    def on_cleanup(self) -> None:
        self._unsubscribe()
        self._latest.reset()

    def _on_message(self, message: Any, info: Any = None) -> None:
        self._latest.update(self.twist_of(message), now_ns(self.context.node), self.stamp_of(message))

    def collect_stamped(self) -> tuple[dict[str, Any] | None, int | None, str | None]:
        sample, stamp = self._latest.take_stamped(now_ns(self.context.node), self.params.repeat_last)
        return sample, stamp, None

    def collect(self) -> dict[str, Any] | None:
        return self.collect_stamped()[0]

    def counters(self) -> dict[str, int]:
        return {"received": self._latest.received}
