"""ROS time for plugins: the node's clock, so that ``use_sim_time`` (a bag, a simulator) is followed."""

from __future__ import annotations

import time
from typing import Any


def now_ns(node: Any) -> int:
    """The node clock's now in nanoseconds (simulated time under ``use_sim_time``); wall time without a node."""
    if node is None:
        return time.time_ns()
    return int(node.get_clock().now().nanoseconds)


def stamp_ns(stamp: Any) -> int:
    """Nanoseconds of a builtin_interfaces/Time."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
