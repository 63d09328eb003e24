"""Position measurement: where the robot is, from TF (``global_frame`` → ``robot_base_frame``).

DC reads /tf and /tf_static itself (dc_core.tf_listener). A poll takes the newest pose the whole
chain of frames gives, as Nav2's ``getCurrentPose`` does, waiting up to ``transform_timeout``
seconds for the chain to exist; it runs on the server's worker, so that wait never holds up other
measurements.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from dc_core.logs import BurstLog
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param
from dc_core.tf import Transform, TransformBuffer, TransformError
from dc_core.tf_listener import TfListener

# How often a poll waiting for its transform looks again.
_RETRY_S = 0.01


@dataclass(frozen=True, kw_only=True)
class PositionParams:
    global_frame: str = param("map", doc="Frame the position is given in")
    robot_base_frame: str = param("base_link", doc="The robot's frame")
    transform_timeout: float = param(
        0.1, minimum=0.0, doc="Seconds a poll waits for the transform to become available before it reports nothing"
    )


def wait_for_transform(
    buffer: TransformBuffer, target: str, source: str, timeout_s: float
) -> tuple[Transform | None, str | None]:
    """The newest pose of ``source`` in ``target``, waiting up to ``timeout_s``; else None and the reason."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return buffer.lookup(target, source), None
        except TransformError as exc:
            if time.monotonic() >= deadline:
                return None, str(exc)
        time.sleep(_RETRY_S)


class Position(Measurement[PositionParams]):
    """Robot position x, y and yaw in global_frame, from TF."""

    collect_in_worker = True

    def __init__(self, context: MeasurementContext, params: PositionParams) -> None:
        super().__init__(context, params)
        self.buffer = TransformBuffer()
        self._listener = TfListener(context, self.buffer)
        self._no_transform_log = BurstLog(context.logger.warning, f"measurement {context.name}: no position")
        self.no_transform = 0

    def on_configure(self) -> None:
        self._listener.start()

    def on_cleanup(self) -> None:
        self._listener.stop()
        self.buffer.clear()

    def collect_stamped(self) -> tuple[dict[str, Any] | None, int | None, str | None]:
        p = self.params
        pose, reason = wait_for_transform(self.buffer, p.global_frame, p.robot_base_frame, p.transform_timeout)
        self._no_transform_log.tick()
        if pose is None:
            self.no_transform += 1
            self._no_transform_log.event(1, f"{reason} (waited {p.transform_timeout:g} s)")
            return None, None, None
        # Dated with the time of the transforms it comes from, not the poll's: the newest pose the
        # chain gives lags the clock by the transforms' delivery (more under load), and a record
        # "the robot was there at <date>" must hold.
        stamp = self.buffer.latest_time(p.global_frame, p.robot_base_frame)
        if stamp:
            try:
                pose = self.buffer.lookup(p.global_frame, p.robot_base_frame, stamp)
            except TransformError:
                stamp = 0  # the history moved on between the two calls: the pose found, dated by the poll
        x, y, _ = pose.translation
        return {"x": x, "y": y, "yaw": pose.yaw}, stamp or None, None

    def collect(self) -> dict[str, Any] | None:
        return self.collect_stamped()[0]

    def counters(self) -> dict[str, int]:
        return {
            "no_transform": self.no_transform,
            "tf_time_jumps": self._listener.time_jumps,
            "tf_old_data": self._listener.old_data,
        }
