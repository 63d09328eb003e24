"""destination_server: subscribes to its destinations' inputs, routes records by tag, hands them to delivery.

The input subscriptions are served by the main loop's intake (dc_core.intake), not by rclpy's executor,
which would rebuild its wait set over the node's services and timers for every record. The callback
only parses, routes and submits (the delivery pipeline's ``submit_record`` puts the record on an
in-memory queue); writing to the buffer and sending run in the pipeline's threads.

Topics published by DC's own servers are subscribed transient-local: after a (re)start the server
receives the publishers' history again, and the hop (dc_destinations.hop) drops what the buffer
already holds and counts what was lost (docs/delivery.md, "The hop between servers").

A record on DC's own topics (dc/measurement/*, dc/group/* in its namespace or at the root) reaches a
destination that reads the files records name only while every publisher of that topic is one of DC's servers
(``trust_tags_from``, docs/security.md): a message does not say which publisher sent it, so one
foreign publisher on the topic makes all its records untrusted for those destinations meanwhile.
The announcements of ended hand-off publishers (``dc/handoff_ended``), which make this server count
records as missing, are taken by the same check whatever ``trust_tags_from`` says.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rclpy.qos import QoSProfile
from rclpy.utilities import get_rmw_implementation_identifier

from dc_core.confined_files import ConfinementParams, default_roots
from dc_core.destination import Destination, OutgoingRecord
from dc_core.diagnostics import ERROR, OK, WARN, scrub, secret_values
from dc_core.diagnostics import status as diagnostic_status
from dc_core.errors import ConfigError, DcError
from dc_core.handoff import ENDED_SUFFIX, RESEND_TOPIC, AckPublisher, resend_qos, resent_topic
from dc_core.handoff_marks import ENDED_TOPIC, ended_qos, parse_ended
from dc_core.lifecycle import ManagedServer, PartialTeardown, run_server
from dc_core.logs import BurstLog
from dc_core.plugin import run_hook, run_hook_on_each
from dc_core.qos import CONDITION_QOS, RECORD_HISTORY_DEPTH, subscription_qos
from dc_core.records import MalformedRecord, parse_record
from dc_core.rmw_features import no_sequence_numbers_line, publication_sequence_numbers
from dc_core.stamped_cdr import read_keyed_string_stamped, read_string_stamped
from dc_core.topics import (
    GROUP_TOPIC_PREFIX,
    MEASUREMENT_TOPIC_PREFIX,
    condition_topic,
    published_topics,
    resolve_topic,
)
from dc_core.worker import Outcome
from dc_destinations.commit import Received
from dc_destinations.config import NODE_NAME, DestinationServerConfig, parse_destination_server
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.health import FAILING, HEALTH_QOS, HEALTH_TOPIC, RETRYING
from dc_destinations.health import summary as health_summary
from dc_destinations.hop import HopIntake, HopKey, hop_key, keyed_hop_key, source_key
from dc_destinations.metrics import hop_prometheus_text
from dc_destinations.record_ids import new_record_id
from dc_destinations.routing import RoutingTable
from dc_interfaces.msg import Condition as ConditionMsg
from dc_interfaces.msg import StringStamped

PREVIEW_CHARS = 200
# Keys kept per topic to recognise replays, in histories: a replay is at most one history per
# publisher, so this covers four publishers of one topic (each of DC's own topics has one).
HOP_WINDOW_HISTORIES = 4
# Malformed records logged one by one at the start of a burst; the rest are counted in a summary.
MALFORMED_LINES_PER_BURST = 10
# The nodes whose records may route themselves to file destinations, in this server's namespace.
DC_PUBLISHERS = frozenset({"measurement_server", "group_server"})
# A foreign publisher seen on a topic keeps it untrusted this long after it left: its last records
# may still wait in the subscription's queue, and a message does not say who sent it.
FOREIGN_MEMORY_S = 10.0
# How long a publisher whose node the graph does not know yet (discovery still under way) is
# waited for, once per publisher, before it is taken as foreign.
UNKNOWN_NODE_WAIT_S = 0.5
# Seconds deactivate waits for a running integrity check of the buffer (it only reads the file).
BUFFER_CHECK_DRAIN_S = 2.0


def internal_prefixes(namespace: str) -> tuple[str, ...]:
    """Where DC's own records are, for the server in ``namespace``: its namespace's, and the root's
    (written absolute in a file, other DCs of the domain may publish there too)."""
    own = (resolve_topic(MEASUREMENT_TOPIC_PREFIX, namespace), resolve_topic(GROUP_TOPIC_PREFIX, namespace))
    return tuple(dict.fromkeys((*own, "/" + MEASUREMENT_TOPIC_PREFIX, "/" + GROUP_TOPIC_PREFIX)))


_Received = tuple[list[tuple[str, OutgoingRecord]], HopKey | None]
"""One received record as the pipeline takes it: its copies by destination name, and its hop key."""


@dataclass
class IntakeStats:
    """Counters of what arrived on the input topics, before delivery counts anything."""

    received: int = 0
    malformed: int = 0
    routed: int = 0
    unrouted: Counter[tuple[str, str]] = field(default_factory=Counter)
    # Copies not made for a file destination: the record's publisher was not one of DC's servers.
    untrusted_tags: Counter[tuple[str, str]] = field(default_factory=Counter)
    # Announcements of ended hand-off publishers not acted on: a publisher of that topic was not DC's.
    handoff_announcements_refused: int = 0

    def as_dict(self) -> dict[str, Any]:
        unrouted: dict[str, dict[str, int]] = {}
        for (topic, reason), count in sorted(self.unrouted.items()):
            unrouted.setdefault(topic, {})[reason] = count
        untrusted: dict[str, dict[str, int]] = {}
        for (topic, destination), count in sorted(self.untrusted_tags.items()):
            untrusted.setdefault(topic, {})[destination] = count
        return {
            "received": self.received,
            "malformed": self.malformed,
            "routed": self.routed,
            "unrouted": unrouted,
            "untrusted_tags": untrusted,
            "handoff_announcements_refused": self.handoff_announcements_refused,
        }


class DestinationServer(ManagedServer):
    # Whether the RMW gives publication sequence numbers (dc_core.rmw_features); a test replaces it to
    # see the line of an RMW without them, which the PyPI wheels do not ship.
    sequence_numbers: Callable[[str], bool | None] = staticmethod(publication_sequence_numbers)

    def __init__(self, params_file: str) -> None:
        super().__init__(NODE_NAME, params_file)
        self.config: DestinationServerConfig | None = None
        self.plugins: dict[str, Destination[Any]] = {}
        self.pipeline: DeliveryPipeline | None = None
        self.routing: RoutingTable | None = None
        self.stats = IntakeStats()
        self._debug: set[str] = set()
        # Not `_subscriptions`: rclpy's Node keeps its own list under that name.
        self._subscription_of: dict[str, Any] = {}
        self._internal_topics: dict[str, int] = {}
        self._hop_window = HOP_WINDOW_HISTORIES * RECORD_HISTORY_DEPTH
        self.hop: HopIntake | None = None
        self._hop_loss_log: BurstLog | None = None
        self._hop_log_timer: Any = None
        self._buffer_check_timer: Any = None
        self._buffer_checking = False
        self.acks: AckPublisher | None = None
        self._ended_subscription: Any = None
        # An announcement was refused: once every publisher of ENDED_TOPIC is DC's again, the subscription
        # is made anew, so that the DC servers' announcements (transient local) come again.
        self._ended_refused = False
        self._announcers_named: set[bytes] = set()  # foreign publishers of ENDED_TOPIC logged already
        self._condition_subscriptions: list[Any] = []
        self._malformed_log = BurstLog(
            self.get_logger().error, "records not delivered, malformed", each=MALFORMED_LINES_PER_BURST
        )
        self._untrusted_log = BurstLog(
            self.get_logger().warning, "records kept from file destinations, their publisher is not DC's"
        )
        self._guarded_topics: set[str] = set()
        self._foreign_seen: dict[str, float] = {}  # topic -> when a foreign publisher was last seen on it
        # topic -> the foreign publishers seen on it (gid -> node), for the lines that name them
        self._foreign_nodes: dict[str, dict[bytes, str]] = {}
        self._waited_for: set[bytes] = set()  # publishers of unknown node waited for once already
        # Each destination's health for the lifecycle manager's is_active: sent when it changes, kept
        # for a manager that (re)subscribes.
        self._health_pub = self.create_publisher(StringStamped, HEALTH_TOPIC, HEALTH_QOS)
        self._health_sent = ""
        self._rmw_checked = False
        self._sent_before: dict[str, tuple[float, int]] = {}  # for records/s on /diagnostics
        self._diagnosing = False
        self._destination_metrics: dict[str, dict[str, Any]] | None = None

    # -- configure / cleanup -----------------------------------------------------------------------
    def configure_server(self) -> None:
        servers = self.read_params_file()
        namespace = self.get_namespace()
        config = parse_destination_server(servers[NODE_NAME], NODE_NAME, namespace)
        self.config = config
        self._internal_topics = self._published_by_dc(servers, namespace)
        self._hop_window = HOP_WINDOW_HISTORIES * max([RECORD_HISTORY_DEPTH, *self._internal_topics.values()])
        log = self.get_logger()
        self.apply_node_params(config.node, config.warnings)

        config = dataclasses.replace(config, destinations=self._with_default_roots(config, servers))
        self.config = config
        for d in config.destinations:
            context = self.plugin_context(d.name)
            plugin: Destination[Any] = d.plugin_class(context, d.plugin_params)
            run_hook(f"destination {d.name} ({d.common.plugin})", plugin, "on_configure")
            self.plugins[d.name] = plugin
            c = d.common
            time_key = f"{c.time_key!r} ({c.time_format})" if c.time_key else "none"
            log.info(f"destination {d.name} ({c.plugin}) <- {', '.join(c.inputs)}; time key {time_key}")
            if c.debug:
                self._debug.add(d.name)
        self.routing = RoutingTable.from_destinations(config.destinations)
        self._guarded_topics = set()
        if config.node.trust_tags_from == "dc_servers":
            self._guarded_topics = {
                topic
                for topic in self.routing.topics
                if (topic.startswith(internal_prefixes(namespace)) or topic in self._internal_topics)
                and self.routing.has_trusted_only(topic)
            }
        self.pipeline = DeliveryPipeline(
            config.node.flb,
            {d.name: (self.plugins[d.name], d.delivery) for d in config.destinations},
            self.get_logger(),
            seen_window=self._hop_window,
            supervisor=self.supervisor,
            saved_files_roots=self._save_folders(servers),
        )
        # At configure: a buffer another process owns fails configure, with the owner named.
        self.pipeline.claim_storage(self.get_namespace())
        self.pipeline.metrics_announce_as = self.metrics_announce_as()
        self.pipeline.add_metrics_section("intake", self.intake_metrics)
        self.pipeline.add_metrics_section("hop", self.hop_metrics)
        self.pipeline.add_prometheus_section(
            lambda: hop_prometheus_text(self.hop_metrics(), self.stats.handoff_announcements_refused)
        )

    def _save_folders(self, servers: dict[str, Any]) -> list[str]:
        """The measurement server's save folder (of this same file), where the disk budget may evict files."""
        try:
            return default_roots(servers.get("measurement_server"))
        except ConfigError as exc:
            # Only the file destinations' allowed_roots then: a budget still evicts nothing outside them.
            self.get_logger().warning(f"disk budget: no saved files counted from the save folder: {exc}")
            return []

    def _with_default_roots(self, config: DestinationServerConfig, servers: dict[str, Any]) -> list[Any]:
        """The destinations, those reading files without ``allowed_roots`` given the measurement
        server's save folder of this same file (dc_core.confined_files.default_roots)."""
        destinations = []
        roots: list[str] | None = None
        for d in config.destinations:
            params = d.plugin_params
            if isinstance(params, ConfinementParams) and not params.allowed_roots:
                if roots is None:
                    roots = default_roots(servers.get("measurement_server"))
                params = dataclasses.replace(params, allowed_roots=roots)
                d = dataclasses.replace(d, plugin_params=params)
            destinations.append(d)
        return destinations

    def _published_by_dc(self, servers: dict[str, dict[str, Any]], namespace: str) -> dict[str, int]:
        """Topics the measurement and group servers of this configuration publish in ``namespace``, with
        their history depth (dc_core.topics.published_topics); what does not read is said and taken as
        other nodes' topics."""
        topics, problems = published_topics(servers, namespace)
        for problem in problems:
            self.get_logger().warning(problem)
        return topics

    def cleanup_server(self) -> None:
        self._destroy_subscriptions()
        if self.pipeline is not None and self.config is not None:
            self.pipeline.stop(self.config.node.flb.grace)  # no-op unless a failed activation left it running
        self._stop_acks()
        # Without a config (a configure that failed parsing it) there is no plugin to clean up.
        for error in self._plugin_hooks("on_cleanup") if self.config is not None else []:
            self.get_logger().error(error)
        self.plugins.clear()
        self._debug.clear()
        if self.pipeline is not None:
            self.pipeline.release_storage()
        self.pipeline = None
        self.routing = None
        self.config = None

    # -- activate / deactivate ---------------------------------------------------------------------
    def activate_server(self) -> None:
        assert self.pipeline is not None and self.routing is not None
        self._diagnosing = False  # a job the last deactivation's worker stop left without its outcome
        for what, plugin in self._named_plugins():
            run_hook(what, plugin, "on_activate")
        # Acks follow commits from the first one on: measurement_server and group_server keep each
        # record they publish until it is acknowledged (dc_core.handoff).
        acks = AckPublisher(self)
        self.acks = acks
        self.pipeline.on_seen_committed = acks.on_commit
        self.pipeline.start()
        # Before the first subscription: the history a publisher replays is checked against these keys.
        hop = HopIntake(self._hop_window)
        loaded = [HopKey(*key) for key in self.pipeline.hop_keys()]
        hop.load(loaded)
        hop.load_loss_totals(self.pipeline.hop_loss_totals())
        acks.tracker.committed(loaded)
        self.hop = hop
        self._hop_loss_log = BurstLog(self.get_logger().error, "records lost before destination_server")
        self._hop_log_timer = self.create_steady_timer(1.0, self._tick_logs)
        check_interval = self.config.node.flb.buffer_check_interval if self.config is not None else 0.0
        if check_interval > 0:  # (the start's check ran in pipeline.start)
            self._buffer_check_timer = self.create_steady_timer(check_interval, self._check_buffer)
        with_history = []
        for topic in self.routing.topics:
            qos = _with_room_for_a_replay(subscription_qos(topic, self._internal_topics))
            on_batch = functools.partial(self._on_batch, topic)
            subscription = self.intake.subscribe_batches(StringStamped, topic, on_batch, qos)
            # Taken as the bytes DDS delivered: the stamp and the text are read from them directly,
            # without building the message's Python objects (dc_core.stamped_cdr).
            subscription.raw = True
            self._subscription_of[topic] = subscription
            if topic in self._internal_topics:
                with_history.append(topic)
        if with_history:
            # Records DC's servers send again after this server was away, for this server alone.
            resent = self.intake.subscribe_batches(StringStamped, RESEND_TOPIC, self._on_resent, resend_qos())
            resent.raw = True
            self._subscription_of[RESEND_TOPIC] = resent
            # The publishers of DC's servers that ended holding records (dc_core.handoff_marks); on the
            # executor, which runs on this thread too, between the intake's turns.
            self._subscribe_ended()
        self.get_logger().info(
            f"listening on {', '.join(self.routing.topics) or 'no topic'}"
            + (f"; with the publishers' history: {', '.join(with_history)}" if with_history else "")
        )
        pipeline = self.pipeline
        for name in pipeline.conditions():  # only_when's conditions, as the measurement server publishes them
            on_state = functools.partial(lambda name, msg: pipeline.set_condition(name, bool(msg.data)), name)
            self._condition_subscriptions.append(
                self.create_subscription(ConditionMsg, condition_topic(name), on_state, CONDITION_QOS)
            )
        acks.send()  # a hello: the publishers send again what this server has not acknowledged
        if not self._rmw_checked:
            self._rmw_checked = True
            self._say_what_the_rmw_lacks()

    def _subscribe_ended(self) -> None:
        if self._ended_subscription is not None:
            self.destroy_subscription(self._ended_subscription)
        self._ended_refused = False
        self._ended_subscription = self.create_subscription(
            StringStamped, ENDED_TOPIC, self._on_ended, ended_qos(depth=10)
        )

    def _say_what_the_rmw_lacks(self) -> None:
        """Once, at the first activation: what a middleware without publication sequence numbers changes."""
        assert self.routing is not None
        identifier = get_rmw_implementation_identifier()
        supported = self.sequence_numbers(identifier)
        if supported:
            return
        if supported is None:
            self.get_logger().info(
                f"whether the middleware {identifier} gives publication sequence numbers is unknown: "
                "records of your own nodes without them are not deduplicated (docs/delivery.md)"
            )
            return
        external = sorted(t for t in self.routing.topics if t not in self._internal_topics)
        log = self.get_logger().warning if external else self.get_logger().info
        log(no_sequence_numbers_line(identifier, external))

    def deactivate_server(self) -> None:
        # Intake stops first, so everything received is committed before the senders stop.
        self._destroy_subscriptions()
        if self._buffer_check_timer is not None:
            self.destroy_timer(self._buffer_check_timer)
            self._buffer_check_timer = None
        # A check running now reads the file on its own connection: waited for briefly, never needed.
        self.stop_worker(BUFFER_CHECK_DRAIN_S)
        self._buffer_checking = False
        if self.pipeline is not None and self.config is not None:
            self.pipeline.stop(self.config.node.flb.grace)
        self._stop_acks()
        errors = self._plugin_hooks("on_deactivate")
        if errors:
            # The server's own part is torn down: it can go on (dc_core.lifecycle).
            raise PartialTeardown("; ".join(errors))

    def _plugin_hooks(self, hook: str) -> list[str]:
        """``hook`` of every plugin, never while its send() runs (DeliveryPipeline.between_sends)."""
        pipeline = self.pipeline
        if pipeline is None:
            return run_hook_on_each(self._named_plugins(), hook)
        errors: list[str] = []
        for name, (what, plugin) in zip(self.plugins, self._named_plugins(), strict=True):
            try:
                pipeline.between_sends(name, functools.partial(run_hook, what, plugin, hook))
            except DcError as exc:
                errors.append(str(exc))
        return errors

    def _named_plugins(self) -> list[tuple[str, Destination[Any]]]:
        assert self.config is not None
        kinds = {d.name: d.common.plugin for d in self.config.destinations}
        return [(f"destination {name} ({kinds[name]})", plugin) for name, plugin in self.plugins.items()]

    def _destroy_subscriptions(self) -> None:
        subscriptions = list(self._subscription_of.values())
        self._subscription_of.clear()
        if self._ended_subscription is not None:
            self.destroy_subscription(self._ended_subscription)
            self._ended_subscription = None
        for subscription in subscriptions:
            # The pipeline still accepts: records already in the reader are committed at its stop.
            self.intake.unsubscribe(subscription, take_queued=True)
        for subscription in self._condition_subscriptions:
            self.destroy_subscription(subscription)
        self._condition_subscriptions.clear()
        if self._hop_log_timer is not None:
            self.destroy_timer(self._hop_log_timer)
            self._hop_log_timer = None
        self._tick_logs()

    def _check_buffer(self) -> None:
        """The periodic integrity check of the buffer file, on the worker: it reads the whole file."""
        pipeline = self.pipeline
        if pipeline is None or self._buffer_checking:
            return
        self._buffer_checking = True

        def done(outcome: Outcome[str]) -> None:
            self._buffer_checking = False
            if outcome.error is not None:
                self.get_logger().error(f"delivery buffer integrity check failed to run: {outcome.error!r}")

        self.worker.submit(pipeline.check_buffer, done)

    def _stop_acks(self) -> None:
        # After the pipeline's stop: the records it commits then are acknowledged too.
        if self.acks is not None:
            if self.pipeline is not None:
                self.pipeline.on_seen_committed = None
            self.acks.destroy()
            self.acks = None

    # -- intake (the main loop's intake, on the main thread) --------------------------------------------
    def _on_batch(self, topic: str, taken: list[tuple[bytes, Any]], resent: bool = False) -> None:
        """The records one drain took from ``topic`` (or, ``resent``, from the resend topic on behalf of
        ``topic``), in one hand-off to the pipeline."""
        assert self.hop is not None
        received: list[_Received] = []
        keys: set[HopKey] = set()
        trusted = topic not in self._guarded_topics or (
            self._publishers_trusted(topic) and (not resent or self._publishers_trusted(RESEND_TOPIC))
        )
        internal = topic in self._internal_topics
        lows: dict[int, int] = {}
        sources: dict[HopKey, int] = {}
        for serialised, info in taken:
            low = source = 0
            key: HopKey | None
            if internal:
                stamp_ns, text, frame_id = read_keyed_string_stamped(serialised)
                keyed = keyed_hop_key(topic, frame_id)
                if keyed is not None:
                    key, low, source = keyed
                    lows[key.source_ns] = max(low, lows.get(key.source_ns, 0))
                else:
                    key = hop_key(topic, info)
            else:
                key = hop_key(topic, info)
                stamp_ns, text = read_string_stamped(serialised)
            if key is not None:
                if key in keys:  # twice in one batch: the hop has not been told of the first yet
                    self.hop.count_duplicate(topic)
                    continue
                keys.add(key)
            one = self._receive(topic, text, stamp_ns, key, trusted, low, source)
            if one is not None:
                received.append(one)
                if source and key is not None:
                    position = source_key(key, 0)
                    sources[position] = max(source, sources.get(position, 0))
        if not internal:
            received = _publisher_positions_only(received)
        # Committed with the records: where the source of each publisher was, for the count after
        # a restart of that publisher (dc_destinations.hop, "source").
        received.extend(([], position._replace(seq=seq)) for position, seq in sources.items())
        # And up to where a publisher's drops were counted, so that the next run does not count them again.
        received.extend(([], mark) for mark in self.hop.take_settled_marks())
        if lows and self.acks is not None:
            for source_ns, low in lows.items():
                self.acks.tracker.saw(topic, -source_ns, low)
        self._hand_over(received)

    def _on_ended(self, msg: Any) -> None:
        """A server announces its publishers of an earlier run that ended holding records not acknowledged:
        what of theirs never arrived is counted, and that it was is committed (then acknowledged)."""
        if self.hop is None:
            return
        if not self._publishers_trusted(ENDED_TOPIC):
            self._refuse_announcement()
            return
        parsed = parse_ended(msg.data)
        if parsed is None:
            return
        server, ended = parsed
        settled: list[_Received] = []
        losses: list[str] = []
        total = 0
        for one in ended:
            if one.topic not in self._internal_topics or one.topic not in self._subscription_of:
                continue  # not read here (any more): nothing of it was expected
            counted = self.hop.writer_ended(one.topic, one.writer, one.high, one.acked)
            settled.append(([], HopKey(one.topic + ENDED_SUFFIX, -one.writer, one.high)))
            if counted is not None:
                first, lost = counted
                total += lost
                losses.append(f"{one.topic} {lost} (publisher {one.writer:x}, numbers {first}..{one.high})")
        if total:
            self.get_logger().warning(
                f"{total} records of {server} never arrived, not acknowledged when its process ended (killed?); "
                f"counted in missing: {', '.join(losses)}"
            )
        elif losses:
            self.get_logger().info(f"{server}'s publishers of its last run ended; all their records arrived")
        self._hand_over(settled)

    def _refuse_announcement(self) -> None:
        """An announcement while a publisher of ENDED_TOPIC is not one of DC's servers: any of them may have
        sent it, and it would make this server count records as missing and settle their publisher for good
        (a later real end of it would go uncounted). Nothing of it is used; DC's own announcements come
        again once the foreign publishers left (:meth:`_tick_logs`)."""
        self.stats.handoff_announcements_refused += 1
        self._ended_refused = True
        for gid, node in self._foreign_nodes.get(ENDED_TOPIC, {}).items():
            if gid not in self._announcers_named:
                self._announcers_named.add(gid)
                self.get_logger().warning(
                    f"{ENDED_TOPIC}: announcement of ended publishers refused, counted in "
                    f"handoff_announcements_refused: {node} publishes there and is not one of DC's servers "
                    f"(docs/security.md); announcements are taken again {FOREIGN_MEMORY_S:g} s after it left"
                )

    def _on_resent(self, taken: list[tuple[bytes, Any]]) -> None:
        """Records sent again by their publisher (dc_core.handoff), each handled as if from its own topic."""
        by_topic: dict[str, list[tuple[bytes, Any]]] = {}
        for serialised, info in taken:
            topic = resent_topic(read_keyed_string_stamped(serialised)[2])
            if topic is not None and topic in self._internal_topics and topic in self._subscription_of:
                by_topic.setdefault(topic, []).append((serialised, info))
        for topic, records in by_topic.items():
            # Whoever publishes on the resend topic speaks for the topic a record names: trusted by tags
            # only while every publisher there is DC's too.
            self._on_batch(topic, records, resent=True)

    def _receive(
        self,
        topic: str,
        text: str,
        stamp_ns: int,
        key: HopKey | None,
        trusted: bool = True,
        low: int = 0,
        source: int = 0,
    ) -> _Received | None:
        """What the pipeline takes of one record: its copies and its key; None for a duplicate."""
        assert self.hop is not None and self.routing is not None
        verdict = self.hop.check(topic, key, low, source)
        if verdict.duplicate:
            return None
        if verdict.skipped:
            assert self._hop_loss_log is not None
            last = verdict.first_skipped + verdict.skipped - 1
            if verdict.source:
                numbers = "its source's records (across a restart of the publisher forwarding them), numbers"
            elif key is not None and key.source_ns < 0:
                numbers = "its publisher's records"
            else:
                numbers = "publication sequence numbers"
            self._hop_loss_log.event(
                verdict.skipped, f"{topic}: {numbers} {verdict.first_skipped}..{last} never arrived"
            )
        self.stats.received += 1
        if stamp_ns == 0:
            # An unstamped message (a bare `ros2 topic pub`) would otherwise be dated 1970.
            stamp_ns = self.get_clock().now().nanoseconds
        try:
            record = parse_record(text)
            routed = self.routing.route(topic, record, stamp_ns, new_record_id, trusted)
        except MalformedRecord as exc:
            self._malformed(topic, text, str(exc))
            return [], key
        if routed.refused:
            self._untrusted(topic, routed.refused)
        if routed.unrouted_reason is not None:
            self._unrouted(topic, routed.unrouted_reason, record)
            return [], key
        self.stats.routed += 1
        if self._debug:
            for name, outgoing in routed.deliveries:
                if name in self._debug:
                    self.get_logger().info(f"{name} <- {outgoing.to_json()}")
        return routed.deliveries, key

    def _tick_logs(self) -> None:
        if self.acks is not None:
            self.acks.send()  # once a second besides the commits': also the hello of a publisher restarted
        if self._hop_loss_log is not None:
            self._hop_loss_log.tick()
        self._malformed_log.tick()
        self._untrusted_log.tick()
        # Between records too: a publisher that sends and leaves at once is still seen here.
        for topic in self._guarded_topics:
            self._publishers_trusted(topic)
        if self._ended_subscription is not None:
            trusted = self._publishers_trusted(ENDED_TOPIC)
            if trusted:
                self._announcers_named.clear()
            if trusted and self._ended_refused:
                self.get_logger().info(f"{ENDED_TOPIC}: every publisher is DC's again; its announcements taken again")
                self._subscribe_ended()
        self._report_health()

    def _publishers_trusted(self, topic: str) -> bool:
        """Whether every publisher of ``topic`` is one of DC's servers of this namespace, and has been for
        FOREIGN_MEMORY_S. The graph's node names are what nodes claim: without SROS2 a node can claim
        to be measurement_server (docs/security.md says so)."""
        now = time.monotonic()
        foreign, unknown = self._foreign_publishers(topic)
        if unknown and not foreign:
            deadline = now + UNKNOWN_NODE_WAIT_S
            while unknown and not foreign and time.monotonic() < deadline:
                time.sleep(0.02)  # discovery runs in the middleware's threads: nothing to await here
                foreign, unknown = self._foreign_publishers(topic)
            self._waited_for.update(unknown)
        if foreign or unknown:
            self._foreign_seen[topic] = time.monotonic()
            named = self._foreign_nodes.setdefault(topic, {})
            named.update(foreign)
            named.update((gid, "a node the graph does not name") for gid in unknown)
            return False
        seen = self._foreign_seen.get(topic)
        if seen is not None and now - seen < FOREIGN_MEMORY_S:
            return False
        self._foreign_nodes.pop(topic, None)  # gone: what names them is not kept
        return True

    def _foreign_publishers(self, topic: str) -> tuple[dict[bytes, str], list[bytes]]:
        """The publishers of ``topic`` that are not DC's (gid -> node), and the gids of those whose node
        the graph does not name yet (not waited for before; one already waited for counts as not DC's)."""
        namespace = self.get_namespace()
        foreign: dict[bytes, str] = {}
        unknown = []
        for info in self.get_publishers_info_by_topic(topic):
            if info.node_name in DC_PUBLISHERS and info.node_namespace == namespace:
                continue
            gid = bytes(info.endpoint_gid)
            if info.node_name == "_NODE_NAME_UNKNOWN_" and gid not in self._waited_for:
                unknown.append(gid)
                continue
            foreign[gid] = (
                "a node the graph does not name"
                if info.node_name == "_NODE_NAME_UNKNOWN_"
                else f"node {info.node_namespace.rstrip('/')}/{info.node_name}"
            )
        return foreign, unknown

    def _report_health(self) -> None:
        pipeline = self.pipeline
        if pipeline is None:
            return
        pipeline.check_health()
        text = health_summary(pipeline.destination_health())
        if text != self._health_sent:
            msg = StringStamped()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.data = text
            self._health_pub.publish(msg)
            self._health_sent = text

    # -- /diagnostics (dc_core.diagnostics, docs/diagnostics.md) -------------------------------------
    def unhealthy_reason(self) -> str:
        if self.pipeline is None or self.lifecycle_state != "active":
            return ""
        return self.pipeline.unhealthy_reason()

    def publish_diagnostics(self) -> None:
        pipeline = self.pipeline
        if pipeline is None or self.lifecycle_state != "active":
            super().publish_diagnostics()
            return
        if self._diagnosing:
            return  # the previous one still waits for the buffer: this one would say the same
        self._diagnosing = True

        def done(outcome: Outcome[dict[str, dict[str, Any]]]) -> None:
            self._diagnosing = False
            self._destination_metrics = outcome.value if outcome.error is None else None
            if outcome.error is not None:
                self.get_logger().error(f"destination metrics for /diagnostics failed: {outcome.error!r}")
            super(DestinationServer, self).publish_diagnostics()

        # On the worker: the buffer's counts wait for a group commit in progress, the intake must not.
        self.worker.submit(pipeline.metrics, done)

    def diagnostic_statuses(self) -> list[Any]:
        pipeline, config, metrics = self.pipeline, self.config, self._destination_metrics
        self._destination_metrics = None
        if pipeline is None or config is None or metrics is None or self.lifecycle_state != "active":
            return []
        secrets = [value for d in config.destinations for value in secret_values(d.plugin_params)]
        now = time.monotonic()
        statuses = []
        for name, values in metrics.items():
            health = values["health"]
            state = health["state"]
            sent = int(values["sent"])
            before = self._sent_before.get(name)
            self._sent_before[name] = (now, sent)
            rate = (sent - before[1]) / (now - before[0]) if before is not None and now > before[0] else None
            if not pipeline.sender_alive(name):
                level, message = ERROR, "its sender thread is not running: records wait in the buffer"
            elif state == FAILING:
                level, message = ERROR, f"failing: {scrub(health['reason'], secrets)}"
            elif state == RETRYING:
                level, message = WARN, f"retrying: {scrub(health['reason'], secrets)}"
            elif values.get("held"):
                level, message = OK, values["held"]  # as the configuration asks: no fault
            else:
                level, message = OK, "delivering"
            statuses.append(
                diagnostic_status(
                    f"{self.get_name()}: {name}",
                    level,
                    message,
                    {
                        "state": state,
                        "held": values.get("held", ""),
                        "pending": values["buffered"],
                        "oldest_pending_s": values["oldest_pending_age_s"],
                        "records_per_s": rate,
                        "sent": sent,
                        "retried": values["retried"],
                        "failed": values["failed"],
                        "dropped": values["dropped"],
                        "dead_letters": values["dead_letters"],
                        "failing_for_s": health.get("for_s"),
                        "fix": health.get("fix", ""),
                        "last_error": scrub(values["last_error"], secrets),
                        "last_error_time": values["last_error_time"],
                        "last_delivery": values["last_delivery"],
                    },
                )
            )
        return statuses

    def _hand_over(self, received: list[_Received]) -> None:
        """Submit records with their copies and keys; the keys are remembered once the pipeline took them.

        A record's copies and key go into one commit: a crash cannot leave a destination without its
        copy of a record that is known as seen. A record that reaches no destination is handed over
        too: its key alone is written, so a replay of it is not reported again.
        """
        assert self.pipeline is not None and self.hop is not None
        received = [(copies, key) for copies, key in received if copies or key is not None]
        # What the hop counted lost goes into the buffer's totals with these records' keys.
        losses = self.hop.losses_not_handed_over()
        submitted: list[Received] = [*received, *(([], one) for one in losses)]
        if submitted and self.pipeline.submit_records(submitted):
            self.hop.losses_handed_over(losses)
            for _, key in received:
                self.hop.handled(key)

    def _malformed(self, topic: str, text: str, reason: str) -> None:
        self.stats.malformed += 1
        log = self.get_logger()
        own_line = self._malformed_log.event(1, f"{topic}: {reason}; {len(text)} chars: {text[:PREVIEW_CHARS]!r}")
        if len(text) > PREVIEW_CHARS:
            # The buffer has no place for a record it cannot parse: this line is its only copy. A
            # flood of them (a broken or hostile publisher) is counted, and kept at debug level.
            (log.error if own_line else log.debug)(f"whole record on {topic} not delivered: {text!r}")

    def _untrusted(self, topic: str, destinations: list[str]) -> None:
        for name in destinations:
            self.stats.untrusted_tags[(topic, name)] += 1
        self._untrusted_log.event(
            len(destinations),
            f"{topic}: tagged for {', '.join(destinations)}; a publisher of {topic} is not one of DC's servers "
            "(trust_tags_from: dc_servers, see docs/security.md)",
        )

    def _unrouted(self, topic: str, reason: str, record: dict[str, Any]) -> None:
        key = (topic, reason)
        first = key not in self.stats.unrouted
        self.stats.unrouted[key] += 1
        listeners = self.routing.listeners(topic) if self.routing is not None else []
        tags_text = f"tags {record['tags']!r}" if "tags" in record else "no tags key"
        message = (
            f"record on {topic} reaches no destination: {reason} "
            f"({tags_text}; destinations listening here: {', '.join(listeners) or 'none'})"
        )
        if first:
            # A warning: a tag naming no destination here drops every record tagged so.
            self.get_logger().warning(message + "; further ones are counted (unrouted) and logged at debug level")
        else:
            self.get_logger().debug(message)

    def intake_metrics(self) -> dict[str, Any]:
        return self.stats.as_dict()

    def hop_metrics(self) -> dict[str, Any]:
        """Per input topic: received, duplicates dropped, records known lost (missing) and more."""
        return self.hop.stats() if self.hop is not None else {}


def _publisher_positions_only(received: list[_Received]) -> list[_Received]:
    """``received`` keeping only the keys that end a run of one publisher's numbers.

    A volatile subscription is never replayed, so the keys of its records cannot deduplicate
    anything: what they are kept for is where each publisher was, so that a restarted server counts
    what it missed meanwhile (docs/delivery.md, "Accounting"). The last key of each run of
    consecutive numbers tells that; the others would only cost a row each in the commit.
    """
    kept: list[_Received] = []
    for i, (copies, key) in enumerate(received):
        following = received[i + 1][1] if i + 1 < len(received) else None
        if key is not None and following is not None and following.seq == key.seq + 1:
            key = None  # the next record continues this publisher
        kept.append((copies, key))
    return kept


def _with_room_for_a_replay(qos: QoSProfile) -> QoSProfile:
    """The same QoS with a queue twice the publishers' history.

    A (re)started subscription receives a whole history at once while live records keep coming;
    with a queue only as deep as the history, the server's lag made DDS overwrite some of them
    (measured at 2,000 records/s). The queue costs memory only while records wait in it.
    """
    return QoSProfile(
        history=qos.history,
        depth=2 * qos.depth,
        reliability=qos.reliability,
        durability=qos.durability,
    )


def main() -> int:
    return run_server(DestinationServer)


if __name__ == "__main__":
    sys.exit(main())
