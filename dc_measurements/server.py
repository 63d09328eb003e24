"""measurement_server: loads measurement and condition plugins and publishes their records."""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass, field
from typing import Any

from dc_core.diagnostics import OK, WARN
from dc_core.diagnostics import status as diagnostic_status
from dc_core.handoff import HandoffSender, destination_inputs, forwarded_seq, forwarding
from dc_core.handoff_marks import marks_folder
from dc_core.lifecycle import ManagedServer, PartialTeardown, ServerPluginContext, run_server
from dc_core.measurement import BasePaths, Measurement
from dc_core.paths import expand_env
from dc_core.plugin import Plugin, run_hook, run_hook_on_each
from dc_core.qos import CONDITION_QOS, record_qos
from dc_core.record_history import SizedRecordPublisher, history_metrics
from dc_core.rostime import now_ns
from dc_core.topics import condition_topic
from dc_interfaces.msg import Condition as ConditionMsg
from dc_interfaces.msg import StringStamped
from dc_measurements.condition_runtime import ConditionRuntime
from dc_measurements.config import NODE_NAME, MeasurementServerConfig, parse_measurement_server
from dc_measurements.metadata import next_run_id, resolve_custom_params
from dc_measurements.metrics import measurement_diagnosis, measurement_prometheus_text
from dc_measurements.runner import MeasurementRunner
from dc_measurements.saved_files import base_paths
from dc_measurements.validation import RecordValidator, schema_version

INIT_MATCH_WAIT_S = 2.0
# How long deactivate waits for collections running on the worker.
WORKER_DRAIN_S = 5.0
# Late subscribers (a dashboard, a test) get the current state of a condition at once.
# Records of users' nodes that reach an inactive server (between configure and activate, or while it is
# deactivated) are held for its activation, at most this many; beyond it they are logged as lost.
HELD_WHILE_INACTIVE_MAX = 10_000


@dataclass
class _MeasurementContext(ServerPluginContext):
    """What a measurement or condition sees of the server (dc_core.measurement.MeasurementContext)."""

    paths: BasePaths = field(default_factory=BasePaths)

    def emit(self, record: dict[str, Any], *, stamp_ns: int | None = None, group_key: str | None = None) -> None:
        assert isinstance(self.server, MeasurementServer)
        self.server.emit_from_event(self.name, record, stamp_ns, group_key)


LEVELS = {"ok": OK, "warn": WARN}


class MeasurementServer(ManagedServer):
    def __init__(self, params_file: str) -> None:
        super().__init__(NODE_NAME, params_file)
        self.config: MeasurementServerConfig | None = None
        self.runners: dict[str, MeasurementRunner] = {}
        self.conditions: dict[str, ConditionRuntime] = {}
        self._record_publishers: dict[str, SizedRecordPublisher] = {}
        self._condition_publishers: list[Any] = []
        self._condition_subscriptions: list[Any] = []
        self._collect_timers: dict[str, Any] = {}
        self._active = False
        self._init_pending: list[str] = []
        self._start_deadline = 0.0
        self._init_timer: Any = None
        self._clock_wait_logged = False
        self.handoff: HandoffSender | None = None
        self._diagnosed: dict[str, tuple[float, dict[str, int]]] = {}  # measurement -> (when, counters) last said
        # (measurement, record, stamp, group key, the publisher's sequence number) taken while inactive.
        self._held: list[tuple[str, dict[str, Any], int | None, str | None, int]] = []
        self.held_while_inactive = 0  # all records ever held, for the logs and tests
        self._held_dropped = 0

    # -- configure ---------------------------------------------------------------------------
    def configure_server(self) -> None:
        servers = self.read_params_file()
        section = servers[NODE_NAME]
        namespace = self.get_namespace()
        config = parse_measurement_server(section, NODE_NAME, namespace)
        self.config = config
        self.handoff = HandoffSender(
            self,
            config.node.handoff,
            destination_inputs(servers, namespace),
            marks=marks_folder(namespace, self.get_name()),
        )
        log = self.get_logger()
        self.apply_node_params(config.node, config.warnings)

        custom = resolve_custom_params(config.custom_str_params)
        paths = base_paths(section, config, custom)
        # Last of the checks that can fail: a failed configure does not use up a run id.
        run_id = next_run_id(config.node.run_id)
        log.info(f"run_id={run_id}; base save path {paths.save_local_base_path!r}")

        for name, ccfg in config.conditions.items():
            publisher = self.create_publisher(ConditionMsg, condition_topic(name), CONDITION_QOS)
            self._condition_publishers.append(publisher)
            context = _MeasurementContext(name, self.get_logger().get_child(name), self, paths)
            condition = ccfg.plugin_class(context, ccfg.plugin_params)
            runtime = ConditionRuntime(name, condition, ccfg.common.topic, log, self._state_publisher(publisher))
            run_hook(f"condition {name} ({ccfg.common.plugin})", condition, "on_configure")
            self.conditions[name] = runtime

        for mcfg in config.measurements:
            c = mcfg.common
            measurement_paths = dataclasses.replace(
                paths, remote_prefixes=dict(zip(c.remote_keys, c.remote_prefixes, strict=False))
            )
            context = _MeasurementContext(mcfg.name, self.get_logger().get_child(mcfg.name), self, measurement_paths)
            plugin: Measurement[Any] = mcfg.plugin_class(context, mcfg.plugin_params)
            validator = self._validator(mcfg.name, plugin, c.enable_validator, c.json_schema_path)
            record_publisher = SizedRecordPublisher(
                mcfg.output_topic,
                self._record_writers(mcfg.output_topic),
                self.destroy_lifecycle_publisher,
                history_depth=c.history_depth,
                history_bytes=c.history_bytes,
                record_bytes_estimate=plugin.record_bytes_estimate(),
                logger=log,
            )
            self._record_publishers[mcfg.name] = record_publisher
            runner = MeasurementRunner(
                mcfg,
                plugin,
                self.conditions,
                validator,
                run_id,
                custom,
                self._publish_fn(self.handoff.output(mcfg.output_topic, record_publisher)),
                log,
                clock_ns=lambda: now_ns(self),
                # The shape the records follow: the schema they are checked against, else the plugin's.
                schema_version=validator.version if validator is not None else schema_version(plugin.load_schema()),
            )
            run_hook(f"measurement {mcfg.name} ({c.plugin})", plugin, "on_configure")
            self.runners[mcfg.name] = runner
            log.info(
                f"measurement {mcfg.name} ({c.plugin}) -> {mcfg.output_topic}"
                + (f" every {c.polling_interval} ms" if plugin.timer_driven else " on events")
            )

    def _record_writers(self, topic: str) -> Any:
        def create(depth: int) -> Any:
            return self.create_lifecycle_publisher(StringStamped, topic, record_qos(depth))

        return create

    def _validator(
        self, name: str, plugin: Measurement[Any], enabled: bool, schema_path: str
    ) -> RecordValidator | None:
        if not enabled:
            return None
        if schema_path:
            return RecordValidator.from_file(expand_env(schema_path, f"{NODE_NAME}.{name}.json_schema_path"))
        schema = plugin.load_schema()
        if schema is None:
            self.get_logger().warning(
                f"measurement {name}: enable_validator is true but the plugin has no schema and no json_schema_path "
                "is set: records are not validated"
            )
            return None
        return RecordValidator(schema, f"of {type(plugin).__name__}")

    def _state_publisher(self, publisher: Any) -> Any:
        def publish(active: bool) -> None:
            msg = ConditionMsg()
            msg.data = active
            publisher.publish(msg)

        return publish

    def _publish_fn(self, handoff_publish: Any) -> Any:
        def publish(text: str, group_key: str, stamp_ns: int | None) -> None:
            if stamp_ns is None:
                stamp_ns = now_ns(self)
            # Serialised and published raw by the hand-off, which keeps it until destination_server
            # acknowledges it: rclpy's conversion of a message object cost more than twice as much.
            handoff_publish(stamp_ns, text, group_key)

        return publish

    # -- activate / deactivate -----------------------------------------------------------------
    def activate_server(self) -> None:
        for runtime in self.conditions.values():
            run_hook(f"condition {runtime.name}", runtime.condition, "on_activate")
            if runtime.topic:
                self._condition_subscriptions.append(
                    self.create_subscription(StringStamped, runtime.topic, self._topic_record_callback(runtime), 10)
                )
        self._active = True
        if self.handoff is not None:
            self.handoff.start()
        for name, runner in self.runners.items():
            runner.set_active(True)
            self._record_publishers[name].on_activate(None)
            run_hook(f"measurement {name} ({runner.config.common.plugin})", runner.plugin, "on_activate")
            if runner.plugin.timer_driven:
                self._init_pending.append(name)
        self._publish_held()
        if self._init_pending:
            self._start_deadline = time.monotonic() + INIT_MATCH_WAIT_S
            self._init_timer = self.create_steady_timer(0.02, self._start_collection)
        assert self.config is not None
        self.start_metrics_http(
            self.config.node, self.metrics_document, lambda: measurement_prometheus_text(self.metrics_document())
        )

    def metrics_document(self) -> dict[str, Any]:
        """Per measurement its counters since configure (the HTTP thread reads them: ints, no lock needed)."""
        handoff = self.handoff
        return {
            "measurements": {
                name: {**dataclasses.asdict(runner.stats), **runner.plugin.counters()}
                for name, runner in list(self.runners.items())
            },
            "handoff": handoff.metrics() if handoff is not None else {},
            "history": history_metrics(list(self._record_publishers.values())),
        }

    def diagnostic_statuses(self) -> list[Any]:
        """One status per measurement while active: WARN when records were lost or not made since the last."""
        if self.lifecycle_state != "active":
            self._diagnosed.clear()
            return []
        now = time.monotonic()
        statuses = []
        for name, counters in self.metrics_document()["measurements"].items():
            before = self._diagnosed.get(name)
            self._diagnosed[name] = (now, counters)
            level, message, values = measurement_diagnosis(
                counters, before[1] if before else None, now - before[0] if before else None
            )
            statuses.append(diagnostic_status(f"{self.get_name()}: {name}", LEVELS[level], message, values))
        return statuses

    @staticmethod
    def _topic_record_callback(runtime: ConditionRuntime) -> Any:
        def callback(msg: Any) -> None:
            runtime.on_topic_record(msg.data)

        return callback

    def _start_collection(self) -> None:
        """Start the timers once every output topic is matched (or INIT_MATCH_WAIT_S passed).

        Discovery between processes takes ~0.35 s: a first record published before the
        destination's (or group's) subscription is matched would reach nobody. All timers start
        together, so measurements polled at related intervals stay in phase (a group can match
        their records), and each period counts from the first sample.
        """
        if self.get_parameter("use_sim_time").value and self.get_clock().now().nanoseconds == 0:
            # Simulated time has not started (no /clock yet): a sample now would be dated 1970.
            if not self._clock_wait_logged:
                self.get_logger().info("use_sim_time: waiting for /clock before collecting")
                self._clock_wait_logged = True
            self._start_deadline = time.monotonic() + INIT_MATCH_WAIT_S
            return
        matched = all(self._record_publishers[n].get_subscription_count() > 0 for n in self._init_pending)
        if not matched and time.monotonic() < self._start_deadline:
            return
        if self._init_timer is not None:
            self._init_timer.cancel()
            self.destroy_timer(self._init_timer)
            self._init_timer = None
        names, self._init_pending = self._init_pending, []
        for name in names:
            period = self.runners[name].config.common.polling_interval / 1000.0
            self._collect_timers[name] = self.create_timer(period, lambda n=name: self._tick(n))
        for name in names:
            if self.runners[name].config.common.init_collect:
                self._tick(name)

    def _tick(self, name: str) -> None:
        runner = self.runners[name]
        if runner.plugin.collect_in_worker:
            runner.tick_in_worker(self.worker)
        else:
            started = time.monotonic()
            runner.tick()
            elapsed = time.monotonic() - started
            if elapsed > runner.config.common.polling_interval / 1000.0:
                self.get_logger().warning(
                    f"measurement {name}: collect took {elapsed:.3f} s, longer than its interval, and held up "
                    "the server meanwhile (a plugin whose collect waits should set collect_in_worker)"
                )
        if runner.finished and name in self._collect_timers:
            timer = self._collect_timers.pop(name)
            timer.cancel()
            self.destroy_timer(timer)
            self.get_logger().info(f"measurement {name}: done, no further sample can be published; timer stopped")

    def emit_from_event(self, name: str, record: dict[str, Any], stamp_ns: int | None, group_key: str | None) -> None:
        if not self._active:
            self._hold(name, record, stamp_ns, group_key)
            return
        self.runners[name].emit(record, stamp_ns, group_key)

    def _hold(self, name: str, record: dict[str, Any], stamp_ns: int | None, group_key: str | None) -> None:
        # A record a user's node published (a forwarded one) was acknowledged to it by DDS: dropping it
        # here would lose it with nothing counting it. What a sensor measurement saw while inactive is
        # not collected, as deactivation means.
        seq = forwarded_seq()
        if not seq:
            return
        if len(self._held) >= HELD_WHILE_INACTIVE_MAX:
            self._held_dropped += 1
            return
        self._held.append((name, record, stamp_ns, group_key, seq))
        self.held_while_inactive += 1

    def _publish_held(self) -> None:
        held, self._held = self._held, []
        if self._held_dropped:
            self.get_logger().error(
                f"{self._held_dropped} record(s) of your nodes reached measurement_server while it was inactive, "
                f"beyond the {HELD_WHILE_INACTIVE_MAX} it holds: lost (destination_server counts them as missing "
                "by the jump in their publishers' numbers)"
            )
            self._held_dropped = 0
        for name, record, stamp_ns, group_key, seq in held:
            runner = self.runners.get(name)
            if runner is None:
                continue
            forwarding(seq)
            try:
                runner.emit(record, stamp_ns, group_key)
            finally:
                forwarding(0)

    def _log_held_lost(self) -> None:
        lost = len(self._held) + self._held_dropped
        if lost:
            self.get_logger().error(
                f"{lost} record(s) of your nodes reached measurement_server while it was inactive and it stopped "
                "before publishing them: lost (destination_server counts them as missing when their publishers "
                "publish again)"
            )
        self._held.clear()
        self._held_dropped = 0

    def deactivate_server(self) -> None:
        self._active = False
        for runner in self.runners.values():
            runner.set_active(False)
        self.stop_metrics_http()
        self._init_pending.clear()
        if self._init_timer is not None:
            self._init_timer.cancel()
            self.destroy_timer(self._init_timer)
            self._init_timer = None
        for timer in self._collect_timers.values():
            timer.cancel()
            self.destroy_timer(timer)
        self._collect_timers.clear()
        for sub in self._condition_subscriptions:
            self.destroy_subscription(sub)
        self._condition_subscriptions.clear()
        # A plugin is not deactivated under a collection still running on the worker.
        if not self.wait_worker_idle(WORKER_DRAIN_S):
            self.get_logger().warning(
                f"deactivating while {self.worker_jobs_running} collection(s) still run after {WORKER_DRAIN_S:g} s; "
                "their samples are dropped"
            )
        for name in self.runners:
            self._record_publishers[name].on_deactivate(None)
        if self.handoff is not None:
            self.handoff.stop()
        errors = run_hook_on_each(self._named_plugins(), "on_deactivate")
        if errors:
            # The server's own part is torn down: it can go on (dc_core.lifecycle).
            raise PartialTeardown("; ".join(errors))

    def _named_plugins(self) -> list[tuple[str, Plugin[Any]]]:
        """Measurements, then conditions, each with what names it in a message."""
        named: list[tuple[str, Plugin[Any]]] = [
            (f"measurement {name} ({runner.config.common.plugin})", runner.plugin)
            for name, runner in self.runners.items()
        ]
        named += [(f"condition {name}", runtime.condition) for name, runtime in self.conditions.items()]
        return named

    def cleanup_server(self) -> None:
        self._active = False
        self._log_held_lost()
        if not self.stop_worker(WORKER_DRAIN_S):
            self.get_logger().warning(f"cleanup: jobs of plugins still ran after {WORKER_DRAIN_S:g} s")
        for error in run_hook_on_each(self._named_plugins(), "on_cleanup"):
            self.get_logger().error(error)
        if self.handoff is not None:
            self.handoff.close()
            self.handoff = None
        for name in self.runners:
            self._record_publishers[name].destroy()
        for publisher in self._condition_publishers:
            self.destroy_publisher(publisher)
        self.runners.clear()
        self.conditions.clear()
        self._record_publishers.clear()
        self._condition_publishers.clear()


def main() -> int:
    return run_server(MeasurementServer)


if __name__ == "__main__":
    sys.exit(main())
