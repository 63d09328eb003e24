"""A record topic's history bounded in bytes (dc_core.record_history): the depth rule, the replacement
of the DDS writer, and what a late subscriber really receives from DDS."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode

from dc_core.qos import record_qos
from dc_core.record_history import DEFAULT_HISTORY_BYTES, SizedRecordPublisher, history_depth_for
from dc_core.stamped_cdr import write_string_stamped
from dc_interfaces.msg import StringStamped

DEADLINE_S = 10.0
KIB = 1024
MIB = 1024 * KIB


def test_depth_rule() -> None:
    assert history_depth_for(300, 1000, DEFAULT_HISTORY_BYTES) == 1000  # small records: the count bounds
    assert history_depth_for(MIB, 1000, DEFAULT_HISTORY_BYTES) == 64
    assert history_depth_for(100 * MIB, 1000, DEFAULT_HISTORY_BYTES) == 1  # never below 1
    assert history_depth_for(MIB, 1000, 0) == 1000  # 0: no byte bound


class FakeWriter:
    """What SizedRecordPublisher uses of a lifecycle publisher; matched and acknowledged on demand."""

    def __init__(self, depth: int) -> None:
        self.depth = depth
        self.published: list[bytes] = []
        self.subscriptions = 0
        self.acked = False
        self.active = False
        self.destroyed = False

    def publish(self, serialised: bytes) -> None:
        assert self.active and not self.destroyed
        self.published.append(serialised)

    def get_subscription_count(self) -> int:
        return self.subscriptions

    def on_activate(self, state: Any) -> None:
        self.active = True

    def on_deactivate(self, state: Any) -> None:
        self.active = False

    def wait_for_all_acked(self, timeout: Any) -> bool:
        return self.acked


class Writers:
    def __init__(self, subscriptions: int = 1) -> None:
        self.made: list[FakeWriter] = []
        self.subscriptions = subscriptions

    def create(self, depth: int) -> FakeWriter:
        writer = FakeWriter(depth)
        self.made.append(writer)
        return writer

    @staticmethod
    def destroy(writer: FakeWriter) -> None:
        writer.destroyed = True


def held_by_dds(writers: Writers) -> int:
    """What the writers not destroyed hold: the last ``depth`` records each, as KEEP_LAST does."""
    return sum(sum(map(len, w.published[-w.depth :])) for w in writers.made if not w.destroyed)


def test_a_larger_record_replaces_the_writer_once_the_new_one_is_matched_and_the_old_once_acknowledged() -> None:
    writers = Writers()
    sized = SizedRecordPublisher(
        "/t", writers.create, writers.destroy, history_depth=1000, history_bytes=100 * KIB, clock=lambda: 0.0
    )
    sized.on_activate(None)
    first = writers.made[0]
    first.subscriptions = 1
    assert first.depth == 1000
    for _ in range(5):
        sized.publish(b"s" * 100)
    big = b"b" * (10 * KIB)
    sized.publish(big)
    # A new writer of depth 10 waits for its subscriber; meanwhile the old one takes the records.
    assert [w.depth for w in writers.made] == [1000, 10] and sized.depth == 10
    assert writers.made[1].active and first.published[-1] == big
    writers.made[1].subscriptions = 1
    sized.publish(big)
    assert writers.made[1].published == [big]
    assert not first.destroyed  # until its subscribers acknowledged what it holds
    first.acked = True
    sized.publish(big)
    assert first.destroyed
    for _ in range(50):
        sized.publish(big)
    assert held_by_dds(writers) == sized.held_bytes() <= 100 * KIB
    assert sized.replaced == 1


def test_the_bound_holds_while_the_new_writer_waits_for_its_subscribers() -> None:
    writers = Writers()
    sized = SizedRecordPublisher(
        "/t", writers.create, writers.destroy, history_depth=1000, history_bytes=100 * KIB, clock=lambda: 0.0
    )
    sized.on_activate(None)
    writers.made[0].subscriptions = 1
    big = b"b" * (10 * KIB)
    for _ in range(30):  # the new writer is never matched (a subscriber slow to discover it)
        sized.publish(big)
        # Each writer within the bound; the old one lives on until its records are acknowledged.
        assert all(sum(map(len, w.published[-w.depth :])) <= 100 * KIB for w in writers.made)
        assert held_by_dds(writers) == sized.held_bytes() <= 2 * 100 * KIB
    assert writers.made[1].published  # it took over at the bound
    writers.made[0].acked = True
    sized.publish(big)
    assert held_by_dds(writers) <= 100 * KIB


def test_a_single_record_above_history_bytes_is_still_kept_once() -> None:
    writers = Writers()
    sized = SizedRecordPublisher(
        "/t", writers.create, writers.destroy, history_depth=1000, history_bytes=KIB, clock=lambda: 0.0
    )
    sized.on_activate(None)
    sized.publish(b"x" * (4 * KIB))
    sized.publish(b"x" * (4 * KIB))
    assert sized.depth == 1
    assert held_by_dds(writers) == sized.held_bytes() == 4 * KIB  # one record, the newest


def test_a_plugin_estimate_sizes_the_first_writer() -> None:
    writers = Writers()
    SizedRecordPublisher(
        "/t", writers.create, writers.destroy, history_depth=1000, history_bytes=64 * MIB, record_bytes_estimate=MIB
    )
    assert [w.depth for w in writers.made] == [64]


# -- DDS: what a late subscriber receives -----------------------------------------------------------


@pytest.fixture
def nodes() -> Iterator[tuple[LifecycleNode, Any, SingleThreadedExecutor]]:
    """A lifecycle node (the server's side) and a node in another context (another participant)."""
    server_context, peer_context = Context(), Context()
    rclpy.init(context=server_context)
    rclpy.init(context=peer_context)
    server = LifecycleNode(f"history_{uuid.uuid4().hex[:8]}", context=server_context)
    peer = rclpy.create_node(f"late_{uuid.uuid4().hex[:8]}", context=peer_context)
    executor = SingleThreadedExecutor(context=peer_context)
    executor.add_node(peer)
    try:
        yield server, peer, executor
    finally:
        executor.shutdown()
        peer.destroy_node()
        server.destroy_node()
        rclpy.shutdown(context=peer_context)
        rclpy.shutdown(context=server_context)


def late_subscriber_receives(peer: Any, executor: SingleThreadedExecutor, topic: str, expected: int) -> list[Any]:
    """What a transient-local subscriber that joins now gets from the history (all of it, once ``expected`` came)."""
    received: list[Any] = []
    peer.create_subscription(StringStamped, topic, received.append, record_qos(1000))
    deadline = time.monotonic() + DEADLINE_S
    while len(received) < expected and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    # The history arrives in one burst: a little longer shows that nothing beyond it comes.
    settle = time.monotonic() + 0.5
    while time.monotonic() < settle:
        executor.spin_once(timeout_sec=0.05)
    return received


def test_late_subscriber_gets_at_most_history_bytes_of_large_records_and_all_small_ones(
    nodes: tuple[LifecycleNode, Any, SingleThreadedExecutor],
) -> None:
    server, peer, executor = nodes
    topics = {
        "large": f"/dc/measurement/large_{uuid.uuid4().hex[:8]}",
        "small": f"/dc/measurement/small_{uuid.uuid4().hex[:8]}",
    }

    def create(topic: str) -> Any:
        return lambda depth: server.create_lifecycle_publisher(StringStamped, topic, record_qos(depth))

    sized = {
        kind: SizedRecordPublisher(
            topic, create(topic), server.destroy_lifecycle_publisher, history_depth=1000, history_bytes=MIB
        )
        for kind, topic in topics.items()
    }
    for publisher in sized.values():
        publisher.on_activate(None)
    blob = "x" * (100 * KIB)
    for i in range(30):
        sized["large"].publish(write_string_stamped(i, f'{{"i": {i}, "blob": "{blob}"}}', ""))
    for i in range(1200):
        sized["small"].publish(write_string_stamped(i, f'{{"i": {i}}}', ""))
    # No subscriber ever matched: the replaced writer took over at the bound and the old one is gone.
    assert sized["large"].depth == 10 and sized["small"].depth == 1000

    large = late_subscriber_receives(peer, executor, topics["large"], 10)
    assert 1 <= len(large) <= 10
    assert sum(len(m.data) for m in large) <= MIB
    assert [int(m.header.stamp.nanosec) for m in large] == list(range(30 - len(large), 30))  # the newest
    small = late_subscriber_receives(peer, executor, topics["small"], 1000)
    assert len(small) == 1000
    for publisher in sized.values():
        publisher.destroy()
