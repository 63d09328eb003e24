"""Subscriptions whose messages a server's main loop takes itself, outside rclpy's executor.

rclpy's ``SingleThreadedExecutor`` gathers every entity of its nodes, enters each handle and builds a
new wait set at every wake-up. A lifecycle node has about a dozen services and a few timers, and at
robot rates records arrive one per wake-up, so that per-wake Python work was most of
destination_server's CPU (docs/performance.md). An :class:`Intake` waits on its subscriptions alone,
takes every message already queued on a ready one, and leaves services and timers to the executor.
:meth:`Intake.take_or_notice` waits on the executor's entities in the same wait set without handling
them, so that a server sleeps until a record, a request, a timer or a finished job needs it, and the
executor gets a non-blocking turn only then.

Both run on the server's main thread, one after the other: a transition never runs while a record
is being handled, exactly as when the executor ran everything.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.executors import ExternalShutdownException
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.subscription import Subscription

# Messages taken from one subscription per wake-up: under a flood, a single busy topic must not
# keep the executor's turn or the other topics waiting for long.
DRAIN_MAX = 256

MessageCallback = Callable[[Any, Any], None]
"""Called with the message and its ``MessageInfo`` (source timestamp, publication sequence number)."""

BatchCallback = Callable[[list[tuple[Any, Any]]], None]
"""Called with every ``(message, MessageInfo)`` one drain took from a subscription, oldest first."""


class Wake(NamedTuple):
    """What one :meth:`Intake.take_or_notice` found."""

    executor_work: bool
    """The executor has something to do (or the wait timed out): give it a turn."""
    records: int
    """Records handed to their callbacks."""
    more_queued: bool
    """A subscription still had records when its drain stopped at ``drain_max``."""


class _TakenByIntake(CallbackGroup):
    """A callback group whose subscriptions the executor never waits on nor runs: the intake takes their messages.

    Their QoS event handlers (rclpy's "incompatible QoS" warning, say) share the group and stay the
    executor's, as in a reentrant group.
    """

    def can_execute(self, entity: Any) -> bool:
        return not isinstance(entity, Subscription)

    def beginning_execution(self, entity: Any) -> bool:
        return not isinstance(entity, Subscription)

    def ending_execution(self, entity: Any) -> None:
        return None


class Intake:
    """The subscriptions of one node that its server's main loop serves itself (see the module doc)."""

    def __init__(self, node: Node, *, drain_max: int = DRAIN_MAX) -> None:
        self._node = node
        self._group = _TakenByIntake()
        self._drain_max = drain_max
        self._callback_of: dict[Subscription, Callable[..., None]] = {}
        self._batched: set[Subscription] = set()
        self._wait_set: Any = None
        self._wait_set_size = -1
        self._combined: Any = None
        self._combined_counts: tuple[int, ...] = ()

    @property
    def active(self) -> bool:
        """Whether there is anything to wait on."""
        return bool(self._callback_of)

    def subscribe(
        self, msg_type: Any, topic: str, callback: MessageCallback, qos: QoSProfile, *, raw: bool = False
    ) -> Subscription:
        """A subscription of the node (``ros2 node info`` lists it there) served by this intake.

        ``raw``: the callback gets the serialised message (bytes, CDR), not deserialised.
        """
        return self._subscribe(msg_type, topic, callback, qos, raw=raw)

    def _subscribe(
        self, msg_type: Any, topic: str, callback: Callable[..., None], qos: QoSProfile, *, raw: bool = False
    ) -> Subscription:
        # rclpy would call the callback itself only through an executor, which never runs this group.
        subscription = self._node.create_subscription(
            msg_type, topic, _never_called, qos, callback_group=self._group, raw=raw
        )
        self._callback_of[subscription] = callback
        return subscription

    def subscribe_batches(self, msg_type: Any, topic: str, callback: BatchCallback, qos: QoSProfile) -> Subscription:
        """:meth:`subscribe`, with ``callback`` called once per drain with all the messages it took.

        For a server that handles records in bulk: per record, it saves a call and lets the work
        of a batch (a hand-off to another thread, say) be done once. A callback that raises loses
        the rest of its batch, so it must handle each message's errors itself.
        """
        subscription = self._subscribe(msg_type, topic, callback, qos)
        self._batched.add(subscription)
        return subscription

    def unsubscribe(self, subscription: Subscription, *, take_queued: bool = False) -> None:
        """Destroy ``subscription``; with ``take_queued``, what DDS has already delivered to it goes to its
        callback first (its publisher counts those as received: destroyed with the reader, they would be lost)."""
        if take_queued:
            while self._drain(subscription) >= self._drain_max:
                pass  # a full drain may have left more
        self._callback_of.pop(subscription, None)
        self._batched.discard(subscription)
        self._node.destroy_subscription(subscription)

    def take(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for a message, then hand every queued one to its callback.

        Returns the number of messages handed over. A callback that raises stops this call; the
        messages still queued are taken at the next one.
        """
        subscriptions = list(self._callback_of)
        if not subscriptions:
            return 0
        wait_set = self._wait_set_for(len(subscriptions))
        wait_set.clear_entities()
        for subscription in subscriptions:
            wait_set.add_subscription(subscription.handle)
        wait_set.wait(int(timeout_s * 1e9))
        if not self._node.context.ok():
            raise ExternalShutdownException()
        ready = wait_set.get_ready_entities("subscription")
        if not ready:
            return 0
        taken = 0
        for subscription in subscriptions:
            if subscription.handle.pointer in ready:
                taken += self._drain(subscription)
        return taken

    @property
    def node(self) -> Node:
        return self._node

    def take_or_notice(self, timeout_s: float, nodes: Sequence[Node], also: Sequence[Intake] = ()) -> Wake:
        """Wait up to ``timeout_s`` for a record or for work of the executor serving ``nodes``.

        Records are handed to their callbacks here, those of the intakes ``also`` too (other nodes
        served by the same loop, as in dc-bringup's single-process mode). ``executor_work`` is True
        when the executor has something to do (a request, a due timer, a message of another
        subscription, a QoS event, a guard condition) or the wait timed out: the caller then gives
        the executor a turn. Nothing but records is taken, so the executor finds the rest still
        ready; guard conditions, which a wait consumes, are triggered again for it.
        """
        mine = {s.handle.pointer: (intake, s) for intake in (self, *also) for s in intake._callback_of}
        subscriptions: list[Any] = []
        timers: list[Any] = []
        clients: list[Any] = []
        services: list[Any] = []
        guards: list[GuardCondition] = []
        waitables: list[Any] = []
        for node in nodes:
            subscriptions.extend(node.subscriptions)
            timers.extend(node.timers)
            clients.extend(node.clients)
            services.extend(node.services)
            guards.extend(node.guards)
            waitables.extend(node.waitables)
        counts = [len(subscriptions), len(guards), len(timers), len(clients), len(services), 0]
        for waitable in waitables:
            n = waitable.get_num_entities()
            for i, more in enumerate((n.num_subscriptions, n.num_guard_conditions, n.num_timers,
                                      n.num_clients, n.num_services, n.num_events)):  # fmt: skip
                counts[i] += more
        wait_set = self._combined_wait_set(tuple(counts))
        for subscription in subscriptions:
            wait_set.add_subscription(subscription.handle)
        for guard in guards:
            wait_set.add_guard_condition(guard.handle)
        for timer in timers:
            wait_set.add_timer(timer.handle)
        for client in clients:
            wait_set.add_client(client.handle)
        for service in services:
            wait_set.add_service(service.handle)
        for waitable in waitables:
            waitable.add_to_wait_set(wait_set)
        wait_set.wait(int(timeout_s * 1e9))
        if not self._node.context.ok():
            raise ExternalShutdownException()
        ready = wait_set.get_ready_entities("subscription")
        records = 0
        more_queued = False
        for pointer in ready:
            taker = mine.get(pointer)
            if taker is not None:
                taken = taker[0]._drain(taker[1])
                records += taken
                more_queued = more_queued or taken >= taker[0]._drain_max
        ready_guards = set(wait_set.get_ready_entities("guard_condition"))
        for guard in guards:
            if guard.handle.pointer in ready_guards:
                guard.trigger()  # consumed by this wait: the executor's own wait must see it too
        executor_work = (
            any(pointer not in mine for pointer in ready)
            or bool(ready_guards)
            or bool(wait_set.get_ready_entities("timer"))
            or bool(wait_set.get_ready_entities("client"))
            or bool(wait_set.get_ready_entities("service"))
            or any(waitable.is_ready(wait_set) for waitable in waitables)
            or not ready
        )
        return Wake(executor_work, records, more_queued)

    def _drain(self, subscription: Subscription) -> int:
        if subscription in self._batched:
            return self._drain_batch(subscription)
        callback = self._callback_of.get(subscription)
        taken = 0
        while callback is not None and taken < self._drain_max:
            try:
                with subscription.handle:
                    message_and_info = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            except InvalidHandle:  # destroyed by a callback of this drain (a deactivate cannot be one)
                break
            if message_and_info is None:
                break
            taken += 1
            callback(message_and_info[0], message_and_info[1])
            callback = self._callback_of.get(subscription)
        return taken

    def _drain_batch(self, subscription: Subscription) -> int:
        callback = self._callback_of.get(subscription)
        if callback is None:
            return 0
        taken: list[tuple[Any, Any]] = []
        handle = subscription.handle
        try:
            with handle:
                while len(taken) < self._drain_max:
                    message_and_info = handle.take_message(subscription.msg_type, subscription.raw)
                    if message_and_info is None:
                        break
                    taken.append(message_and_info)
        except InvalidHandle:  # destroyed by an earlier callback of this wake-up
            pass
        if taken:
            callback(taken)
        return len(taken)

    def _combined_wait_set(self, counts: tuple[int, ...]) -> Any:
        # Made again only when the entities change (a transition, a plugin's subscription): not per record.
        if counts != self._combined_counts:
            self._combined = _rclpy.WaitSet(*counts, self._node.context.handle)
            self._combined_counts = counts
        self._combined.clear_entities()
        return self._combined

    def _wait_set_for(self, size: int) -> Any:
        # rclpy's own wait_for_message builds its wait set the same way; the executor has no API
        # for waiting on a subset of a node's entities.
        if size != self._wait_set_size:
            self._wait_set = _rclpy.WaitSet(size, 0, 0, 0, 0, 0, self._node.context.handle)
            self._wait_set_size = size
        return self._wait_set


def _never_called(message: Any) -> None:
    raise AssertionError("an intake subscription was run by an executor")
