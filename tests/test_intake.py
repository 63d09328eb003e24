"""dc_core.intake and run_server's loop: records taken outside the executor, services and timers still served.

The intake exists for speed (docs/performance.md); these tests hold what a server relies on when it
uses one: every record arrives once, in order, with its MessageInfo; the executor never runs an intake
subscription; a drain is bounded so that services and timers get their turn under a flood; lifecycle
transitions that create and destroy intake subscriptions work through the loop; a failing callback
is logged and the records after it still arrive.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, cast

import pytest
from dc_lifecycle_interfaces.msg import Heartbeat
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from dc_core import lifecycle
from dc_core.intake import DRAIN_MAX, Intake, Wake
from dc_core.lifecycle import HEARTBEAT_QOS, HEARTBEAT_TOPIC, ManagedServer, ServerLoop
from dc_core.testing import RecordingLogger
from tests.ros_util import two_contexts, wait_for

RECORD_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
DEADLINE_S = 15.0


@pytest.fixture
def contexts() -> Iterator[tuple[Context, Context]]:
    with two_contexts() as both:
        yield both


class Peer:
    """A node in the other context: publishes records, and can call a server's lifecycle services."""

    def __init__(self, topic: str, context: Context) -> None:
        self.node = Node(f"dc_peer_{uuid.uuid4().hex[:8]}", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.publisher = self.node.create_publisher(String, topic, RECORD_QOS)
        self._clients: dict[str, Any] = {}

    def spin(self) -> None:
        self.executor.spin_once(timeout_sec=0.02)

    def transition(self, server_name: str, transition_id: int) -> bool:
        client = self._clients.get(server_name)
        if client is None:
            client = self._clients[server_name] = self.node.create_client(ChangeState, f"/{server_name}/change_state")
        assert wait_for(client.service_is_ready, self.spin), "change_state never appeared"
        request = ChangeState.Request()
        request.transition.id = transition_id
        future = client.call_async(request)
        assert wait_for(future.done, self.spin), "change_state never answered"
        return bool(future.result().success)

    def bring_up(self, server_name: str) -> None:
        """Configure and activate a server, then wait until its intake subscribes to the peer's topic."""
        assert self.transition(server_name, Transition.TRANSITION_CONFIGURE)
        assert self.transition(server_name, Transition.TRANSITION_ACTIVATE)
        assert wait_for(lambda: self.publisher.get_subscription_count() == 1, self.spin)

    def publish(self, *texts: str) -> None:
        for text in texts:
            self.publisher.publish(String(data=text))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@dataclass
class Witnessed:
    """A node with an intake subscription and, on the same topic, a witness run by an executor.

    Once the witness has every record, so had the executor the chance to run the intake's
    subscription, had it been in its wait set; and every record is queued for the intake.
    """

    intake: Intake
    taken: list[Any]  # what the intake's callback was given
    witnessed: list[str]
    peer: Peer
    executor: SingleThreadedExecutor

    def spin_executor(self) -> None:
        self.executor.spin_once(timeout_sec=0.02)
        self.peer.spin()

    def publish_and_witness(self, texts: list[str]) -> None:
        assert wait_for(lambda: self.peer.publisher.get_subscription_count() >= 2, self.spin_executor)
        self.peer.publish(*texts)
        assert wait_for(lambda: len(self.witnessed) == len(texts), self.spin_executor), self.witnessed


@contextmanager
def witnessed_intake(
    contexts: tuple[Context, Context], drain_max: int, subscribe: Callable[[Intake, str], list[Any]]
) -> Iterator[Witnessed]:
    """A node whose intake ``subscribe`` subscribes (returning the list its callback fills), its witness and a peer."""
    server_context, other_context = contexts
    topic = f"/dc_test/intake_{uuid.uuid4().hex[:8]}"
    node = Node(f"dc_intake_{uuid.uuid4().hex[:8]}", context=server_context)
    intake = Intake(node, drain_max=drain_max)
    taken = subscribe(intake, topic)
    witnessed: list[str] = []
    node.create_subscription(String, topic, lambda msg: witnessed.append(cast(Any, msg).data), RECORD_QOS)
    executor = SingleThreadedExecutor(context=server_context)
    executor.add_node(node)
    peer = Peer(topic, other_context)
    try:
        yield Witnessed(intake, taken, witnessed, peer, executor)
    finally:
        peer.close()
        executor.shutdown()
        node.destroy_node()


def _each_message(intake: Intake, topic: str) -> list[Any]:
    taken: list[tuple[str, Any]] = []
    intake.subscribe(String, topic, lambda msg, info: taken.append((msg.data, info)), RECORD_QOS)
    return taken


def _batches(intake: Intake, topic: str) -> list[Any]:
    batches: list[list[tuple[str, Any]]] = []
    intake.subscribe_batches(String, topic, lambda taken: batches.append([(m.data, i) for m, i in taken]), RECORD_QOS)
    return batches


@pytest.fixture(params=[DRAIN_MAX, 4], ids=["drain_max", "drain_4"])
def witnessed(request: pytest.FixtureRequest, contexts: tuple[Context, Context]) -> Iterator[Witnessed]:
    with witnessed_intake(contexts, request.param, _each_message) as it:
        yield it


def test_records_reach_the_intake_with_their_message_info_and_never_the_executor(witnessed: Witnessed) -> None:
    texts = [f"record {i}" for i in range(20)]
    witnessed.publish_and_witness(texts)
    assert witnessed.taken == [], "the executor ran an intake subscription"

    taken = witnessed.taken
    assert wait_for(lambda: len(taken) == 20, lambda: witnessed.intake.take(0.05)), taken
    assert [text for text, _ in taken] == texts
    sequence_numbers = [info["publication_sequence_number"] for _, info in taken]
    assert sequence_numbers == sorted(sequence_numbers) and len(set(sequence_numbers)) == 20
    assert all(info["source_timestamp"] > 0 for _, info in taken)
    assert witnessed.intake.take(0.0) == 0, "a record was handed over twice"


@pytest.mark.parametrize("witnessed", [4], indirect=True, ids=["drain_4"])
def test_a_drain_is_bounded_and_the_rest_comes_at_the_next_take(witnessed: Witnessed) -> None:
    witnessed.publish_and_witness([str(i) for i in range(10)])
    assert witnessed.intake.take(1.0) == 4
    assert witnessed.intake.take(1.0) == 4
    assert witnessed.intake.take(1.0) == 2
    assert [text for text, _ in witnessed.taken] == [str(i) for i in range(10)]


def test_unsubscribing_with_take_queued_hands_over_what_the_reader_holds(contexts: tuple[Context, Context]) -> None:
    # destination_server's stop: records DDS delivered but not yet taken are committed, not destroyed with the reader.
    subscriptions: list[Any] = []

    def subscribe(intake: Intake, topic: str) -> list[Any]:
        taken: list[str] = []
        subscriptions.append(intake.subscribe(String, topic, lambda msg, _: taken.append(msg.data), RECORD_QOS))
        return taken

    with witnessed_intake(contexts, 4, subscribe) as it:
        texts = [str(i) for i in range(10)]
        it.publish_and_witness(texts)
        it.intake.unsubscribe(subscriptions[0], take_queued=True)
        assert it.taken == texts
        assert not it.intake.active


def test_unsubscribing_from_a_callback_stops_the_drain(contexts: tuple[Context, Context]) -> None:
    server_context, other_context = contexts
    topic = f"/dc_test/intake_{uuid.uuid4().hex[:8]}"
    node = Node(f"dc_intake_{uuid.uuid4().hex[:8]}", context=server_context)
    intake = Intake(node)
    taken: list[str] = []

    def on_record(msg: Any, info: Any) -> None:
        taken.append(msg.data)
        if msg.data == "stop":
            intake.unsubscribe(subscription)

    subscription = intake.subscribe(String, topic, on_record, RECORD_QOS)
    peer = Peer(topic, other_context)
    try:
        assert wait_for(lambda: peer.publisher.get_subscription_count() >= 1, peer.spin)
        peer.publish("a", "stop", "b", "c")
        assert wait_for(lambda: "stop" in taken, lambda: intake.take(0.05))
        assert taken == ["a", "stop"]
        assert not intake.active
        assert intake.take(0.01) == 0
    finally:
        peer.close()
        node.destroy_node()


def test_a_batch_subscription_gets_each_drain_in_one_call(contexts: tuple[Context, Context]) -> None:
    with witnessed_intake(contexts, 4, _batches) as it:
        batches, intake = it.taken, it.intake
        texts = [str(i) for i in range(10)]
        it.publish_and_witness(texts)
        assert [intake.take(1.0) for _ in range(3)] == [4, 4, 2]
        assert [len(batch) for batch in batches] == [4, 4, 2]
        assert [text for batch in batches for text, _ in batch] == texts
        sequence_numbers = [info["publication_sequence_number"] for batch in batches for _, info in batch]
        assert sequence_numbers == sorted(sequence_numbers) and len(set(sequence_numbers)) == 10
        assert intake.take(0.0) == 0
        assert len(batches) == 3, "an empty drain called the callback"


class _FakeIntake:
    """What ServerLoop asks of an intake, answering each wait with the next of ``wakes``."""

    active = True

    def __init__(self, wakes: list[Wake], linger_s: float) -> None:
        self.wakes = wakes
        self.node = _FakeNode(linger_s)

    def take_or_notice(self, timeout_s: float, nodes: Any, also: Any = ()) -> Wake:
        return self.wakes.pop(0)


@dataclass
class _FakeNode:
    record_linger_s: float

    def create_guard_condition(self, callback: Any) -> Any:
        return None


class _NoExecutor:
    def get_nodes(self) -> list[Any]:
        return []


@pytest.mark.parametrize(
    ("wake", "linger_s", "lingers"),
    [
        (Wake(executor_work=False, records=3, more_queued=False), 0.05, True),
        (Wake(executor_work=True, records=3, more_queued=False), 0.05, False),  # the executor's turn first
        (Wake(executor_work=False, records=256, more_queued=True), 0.05, False),  # a flood: take the rest now
        (Wake(executor_work=False, records=3, more_queued=False), 0.0, False),  # record_linger 0
    ],
    ids=["records", "executor-work", "more-queued", "linger-0"],
)
def test_the_loop_lets_records_gather_only_while_they_flow_and_nothing_else_waits(
    monkeypatch: pytest.MonkeyPatch, wake: Wake, linger_s: float, lingers: bool
) -> None:
    slept: list[float] = []
    monkeypatch.setattr("dc_core.lifecycle.time", SimpleNamespace(sleep=slept.append))
    monkeypatch.setattr(lifecycle, "run_ready_callbacks", lambda executor, limit: 0)
    loop = ServerLoop(cast(Any, _NoExecutor()), cast(Any, [_FakeIntake([wake], linger_s)]))
    loop.spin_once(1.0)
    assert slept == ([linger_s] if lingers else [])


def test_one_loop_for_several_servers_lingers_as_long_as_the_shortest_asks(monkeypatch: pytest.MonkeyPatch) -> None:
    slept: list[float] = []
    monkeypatch.setattr("dc_core.lifecycle.time", SimpleNamespace(sleep=slept.append))
    records = Wake(executor_work=False, records=1, more_queued=False)
    intakes = [_FakeIntake([records], 0.05), _FakeIntake([], 0.01)]
    ServerLoop(cast(Any, _NoExecutor()), cast(Any, intakes)).spin_once(1.0)
    assert slept == [0.01]


TICK_PERIOD_S = 0.005


class IntakeServer(ManagedServer):
    """A server that, like destination_server, subscribes through its intake while active."""

    def __init__(self, topic: str, context: Context, fail_on: str = "") -> None:
        super().__init__(f"dc_intake_server_{uuid.uuid4().hex[:8]}", "", heartbeat_period=0.05, context=context)
        self.topic = topic
        self.fail_on = fail_on
        self.received: list[str] = []
        self.plugin_received: list[str] = []
        self._subscription: Any = None
        self._plugin_subscription: Any = None
        self.ticks = 0
        self._ticker: Any = None

    def configure_server(self) -> None:
        pass

    def activate_server(self) -> None:
        self._subscription = self.intake.subscribe(String, self.topic, self._on_record, RECORD_QOS)
        # What a plugin may do with the node it is given: an ordinary subscription, run by the executor.
        self._plugin_subscription = self.create_subscription(
            String, self.topic + "_plugin", lambda msg: self.plugin_received.append(cast(Any, msg).data), RECORD_QOS
        )
        # A fast timer, like a measurement's collection.
        self._ticker = self.create_timer(TICK_PERIOD_S, self._tick)

    def _tick(self) -> None:
        self.ticks += 1

    def _on_record(self, msg: Any, info: Any) -> None:
        if msg.data == self.fail_on:
            raise ValueError(f"cannot handle {msg.data!r}")
        self.received.append(msg.data)

    def deactivate_server(self) -> None:
        self.intake.unsubscribe(self._subscription)
        self.destroy_subscription(self._plugin_subscription)
        self.destroy_timer(self._ticker)

    def cleanup_server(self) -> None:
        pass


@pytest.fixture
def served(contexts: tuple[Context, Context]) -> Iterator[tuple[IntakeServer, Peer, RecordingLogger]]:
    """An IntakeServer run by ServerLoop.run in a thread (run_server's loop), and a peer to drive it."""
    server_context, other_context = contexts
    topic = f"/dc_test/intake_{uuid.uuid4().hex[:8]}"
    server = IntakeServer(topic, server_context, fail_on="poison")
    executor = SingleThreadedExecutor(context=server_context)
    executor.add_node(server)
    logger = RecordingLogger()
    stop = threading.Event()
    loop = threading.Thread(target=ServerLoop(executor, server.intake).run, args=(stop, logger), daemon=True)
    loop.start()
    peer = Peer(topic, other_context)
    try:
        yield server, peer, logger
    finally:
        peer.close()
        stop.set()
        loop.join(timeout=5.0)
        assert not loop.is_alive(), "the loop did not stop"
        executor.shutdown()
        server.destroy_node()


def test_transitions_heartbeats_and_records_through_the_server_loop(
    served: tuple[IntakeServer, Peer, RecordingLogger],
) -> None:
    server, peer, logger = served
    beats: list[Any] = []
    peer.node.create_subscription(
        Heartbeat,
        HEARTBEAT_TOPIC,
        lambda m: beats.append(m) if cast(Any, m).node_name == server.get_fully_qualified_name() else None,
        HEARTBEAT_QOS,
    )
    assert peer.transition(server.get_name(), Transition.TRANSITION_CONFIGURE)
    for cycle in range(2):  # the second activation subscribes anew
        assert peer.transition(server.get_name(), Transition.TRANSITION_ACTIVATE)
        assert wait_for(lambda: peer.publisher.get_subscription_count() == 1, peer.spin)
        # Records keep the intake busy; the heartbeat timer must still fire (the executor's turns).
        texts = [f"{cycle}-{i}" for i in range(300)]
        beats_before = len(beats)
        peer.publish(*texts)
        assert wait_for(lambda t=texts: server.received[-300:] == t, peer.spin), server.received[-3:]  # type: ignore[misc]
        assert wait_for(lambda b=beats_before: len(beats) >= b + 3, peer.spin), "no heartbeat while active"  # type: ignore[misc]
        assert beats[-1].state == 3  # active
        assert peer.transition(server.get_name(), Transition.TRANSITION_DEACTIVATE)
        assert wait_for(lambda: peer.publisher.get_subscription_count() == 0, peer.spin), "still subscribed"
        assert not server.intake.active
    assert logger.at("error") == []


def test_a_failing_callback_is_logged_and_the_records_after_it_arrive(
    served: tuple[IntakeServer, Peer, RecordingLogger],
) -> None:
    server, peer, logger = served
    peer.bring_up(server.get_name())
    peer.publish("before", "poison", "after")
    assert wait_for(lambda: server.received == ["before", "after"], peer.spin), server.received
    errors = logger.at("error")
    assert len(errors) == 1 and "cannot handle 'poison'" in errors[0]


def test_the_nodes_own_subscriptions_keep_up_while_the_intake_is_active(
    served: tuple[IntakeServer, Peer, RecordingLogger],
) -> None:
    server, peer, logger = served
    peer.bring_up(server.get_name())
    plugin_publisher = peer.node.create_publisher(String, server.topic + "_plugin", RECORD_QOS)
    assert wait_for(lambda: plugin_publisher.get_subscription_count() == 1, peer.spin)
    assert wait_for(lambda: peer.publisher.get_subscription_count() == 1, peer.spin)
    # 500 messages in the executor's hands, with records arriving meanwhile: at one message per turn
    # (20 turns a second) they would take 25 s.
    texts = [str(i) for i in range(500)]
    for text in texts:
        plugin_publisher.publish(String(data=text))
    peer.publish("record")
    assert wait_for(lambda: server.plugin_received == texts, peer.spin), len(server.plugin_received)
    assert wait_for(lambda: server.received == ["record"], peer.spin)
    assert logger.at("error") == []


def test_timers_fire_at_their_period_while_the_intake_is_active(
    served: tuple[IntakeServer, Peer, RecordingLogger],
) -> None:
    server, peer, _logger = served
    peer.bring_up(server.get_name())
    assert wait_for(lambda: peer.publisher.get_subscription_count() == 1, peer.spin)
    assert server.intake.active
    # rcl skips the periods a timer missed: with a turn every 50 ms (the loop before it slept) instead of one
    # when the timer is due, 400 ticks of a 5 ms timer would take 20 s, beyond wait_for's deadline.
    ticks_before = server.ticks
    assert wait_for(lambda: server.ticks >= ticks_before + 400, peer.spin), server.ticks - ticks_before


def test_qos_events_of_intake_subscriptions_still_reach_the_log(
    served: tuple[IntakeServer, Peer, RecordingLogger], capfd: pytest.CaptureFixture[str]
) -> None:
    # rclpy's default handler logs a publisher whose QoS cannot match; it runs on the executor.
    server, peer, _logger = served
    peer.bring_up(server.get_name())
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    peer.node.create_publisher(String, server.topic, best_effort)
    stderr: list[str] = []

    def seen() -> bool:
        stderr.append(capfd.readouterr().err)
        # The server's side of it (the publisher's own side logs "New subscription discovered ...").
        return f"New publisher discovered on topic '{server.topic}', offering incompatible QoS" in "".join(stderr)

    # A longer deadline: in one loaded full run (CI) the publisher's side logged and the server's had
    # not after 15 s; the server's view of the graph says next time whether it had discovered the publisher.
    assert wait_for(seen, peer.spin, deadline_s=40), (
        f"publishers the server sees on the topic: {server.count_publishers(server.topic)}\n" + "".join(stderr)[-2000:]
    )
