"""Helpers of the tests that drive rclpy nodes in this process."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import rclpy
from rclpy.context import Context

DEADLINE_S = 15.0


def wait_for(condition: Callable[[], bool], spin: Callable[[], object], deadline_s: float = DEADLINE_S) -> bool:
    """Call ``spin`` until ``condition`` holds or the deadline passes; returns the condition."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        if condition():
            return True
        spin()
    return condition()


@contextmanager
def two_contexts() -> Iterator[tuple[Context, Context]]:
    """A server's context and a peer's: two DDS participants, as two processes would have."""
    server_context, peer_context = Context(), Context()
    rclpy.init(context=server_context)
    rclpy.init(context=peer_context)
    try:
        yield server_context, peer_context
    finally:
        rclpy.shutdown(context=peer_context)
        rclpy.shutdown(context=server_context)
