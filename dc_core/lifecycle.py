"""Lifecycle server base: transitions that log and undo on failure, a heartbeat, and a main loop.

Every DC server is an rclpy ``LifecycleNode``. Subclasses implement ``configure_server`` (parse and
build; raise to fail), ``activate_server`` (timers, connections), ``deactivate_server`` (stop intake,
flush) and ``cleanup_server`` (release). A failing transition is logged with its reason and its
result is what the node's state then is (ROS 2's lifecycle design):

- configure or activate that fails is undone and reported as FAILURE: the node is back where it was;
- a teardown (deactivate, cleanup, or the undo of a failed step) that stops part-way leaves the node
  in no state it could go on from: ERROR, and ``on_error`` releases what it can — ``unconfigured``
  if that works, ``finalized`` if not (the lifecycle manager restarts the process either way);
- a teardown that went to its end but one part of which failed (a plugin's own ``on_deactivate``,
  :class:`PartialTeardown`) succeeds, with that part logged at ERROR.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import rclpy
import rclpy.utilities
from dc_lifecycle_interfaces.msg import Heartbeat
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import State
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.executors import (
    ConditionReachedException,
    Executor,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from dc_core.config import load_params
from dc_core.declared_params import declare_read_only
from dc_core.diagnostics import DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, ERROR, OK, WARN, scrub
from dc_core.diagnostics import array as diagnostic_array
from dc_core.diagnostics import status as diagnostic_status
from dc_core.errors import ConfigError, DcError
from dc_core.http_status import StatusServer, start_status_server
from dc_core.intake import Intake
from dc_core.logs import Logger, SeverityLogger
from dc_core.native_stdout import python_only_stdout
from dc_core.node_params import (
    DEFAULT_DIAGNOSTICS_PERIOD_S,
    DEFAULT_HEARTBEAT_PERIOD_S,
    DEFAULT_RECORD_LINGER_S,
    MetricsHttpParams,
    ServerNodeParams,
)
from dc_core.plugin import MessageCallback
from dc_core.private_files import use_private_umask
from dc_core.ros_args import param_sections, process_ros_args, set_process_ros_args, split_ros_args
from dc_core.signals import StopFlag, StopRequest, wake_on_signals
from dc_core.supervision import Supervisor
from dc_core.topics import ros_namespace
from dc_core.worker import Worker

# Relative: the servers and the lifecycle manager of one namespace share it, another DC's are apart.
HEARTBEAT_TOPIC = "dc/heartbeat"
HEARTBEAT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# The heartbeat's state while a server is unhealthy (a thread of it died, dc_core.supervision): the
# lifecycle's own "an error is being handled" state, so Heartbeat.msg needs no new field. The
# lifecycle manager restarts a server that sends it.
HEARTBEAT_STATE_UNHEALTHY = State.TRANSITION_STATE_ERRORPROCESSING
# Most executor callbacks run in one turn while the intake is active; the rest wait for the next turn.
EXECUTOR_TURN_MAX_CALLBACKS = 256
# The shortest wait between two executor turns while the intake is active.
# The longest a server's loop sleeps when nothing happens: signals and work wake it at once, this
# only bounds a wait should a wake-up ever be missed.
IDLE_WAIT_S = 5.0


class PartialTeardown(DcError):
    """Raised by ``deactivate_server`` or ``cleanup_server`` that went to its end when one part of it
    failed (a plugin's own hook): the server is torn down and can go on, so the transition succeeds
    and the part is logged at ERROR. Any other exception of a teardown means it stopped part-way."""


@dataclass
class ServerPluginContext:
    """What a server gives each plugin instance (dc_core.plugin.PluginContext), for every kind."""

    name: str
    logger: Logger
    server: ManagedServer

    @property
    def node(self) -> Any:
        return self.server

    def subscribe(
        self, msg_type: Any, topic: str, callback: MessageCallback, qos: QoSProfile, *, raw: bool = False
    ) -> Any:
        subscription = self.server.intake.subscribe(msg_type, topic, callback, qos, raw=raw)
        try:
            check_remapped_type(self.server, msg_type, topic, subscription.topic_name)
        except ConfigError:
            self.server.intake.unsubscribe(subscription)
            raise
        return subscription

    def unsubscribe(self, subscription: Any, *, take_queued: bool = False) -> None:
        self.server.intake.unsubscribe(subscription, take_queued=take_queued)

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        return self.server.create_timer(period_s, callback)

    def destroy_timer(self, timer: Any) -> None:
        timer.cancel()
        self.server.destroy_timer(timer)

    @property
    def worker(self) -> Worker:
        return self.server.worker

    def start_thread(self, target: Callable[[], Any], name: str) -> threading.Thread:
        return self.server.supervisor.start_thread(target, name=name)


def check_remapped_type(node: Any, msg_type: Any, topic: str, resolved: str) -> None:
    """ConfigError when a remap (``--ros-args -r``) sent ``topic`` to a topic of another type.

    DDS would match nothing there and say nothing. Only the publishers the graph knows when the
    subscription is made can be checked: one that appears later with another type is not seen here.
    """
    if resolved == node.resolve_topic_name(topic, only_expand=True):
        return  # not remapped: a type clash is the publisher's, as for any subscriber
    ours = f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"
    theirs = sorted({info.topic_type for info in node.get_publishers_info_by_topic(resolved)})
    if theirs and ours not in theirs:
        raise ConfigError(
            topic, f"remapped to {resolved}, which carries {', '.join(theirs)}: {ours} expected (check --ros-args -r)"
        )


class ManagedServer(LifecycleNode):
    """A DC server process' node."""

    def __init__(
        self, node_name: str, params_file: str, heartbeat_period: float = DEFAULT_HEARTBEAT_PERIOD_S, **node_kwargs: Any
    ) -> None:
        # node_kwargs reach rclpy's LifecycleNode (e.g. context= for tests with a fresh context).
        super().__init__(node_name, **node_kwargs)
        self.params_file = params_file
        # Every thread of this server runs under its rule: a thread that dies makes the server unhealthy.
        self.supervisor = Supervisor(self.get_logger())
        # Subscriptions for records: the main loop takes them itself (dc_core.intake).
        self.intake = Intake(self)
        # The record_linger parameter (ServerLoop), set at configure.
        self.record_linger_s = DEFAULT_RECORD_LINGER_S
        self._heartbeat_seq = 0
        self._declared_params: set[str] = set()  # DC's settings, as ROS parameters (read_params_file)
        self._heartbeat_pub = self.create_publisher(Heartbeat, HEARTBEAT_TOPIC, HEARTBEAT_QOS)
        # The heartbeat runs in every state: it tells the manager the process is alive. On the steady
        # clock: under use_sim_time a paused or finished bag stops ROS time, not the process.
        self._steady_clock = Clock(clock_type=ClockType.STEADY_TIME)
        self._heartbeat_timer = self.create_timer(heartbeat_period, self._send_heartbeat, clock=self._steady_clock)
        # Like the heartbeat in every state: a server that cannot configure says so there too.
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS)
        self._diagnostics_timer: Any = None
        self.set_diagnostics_period(DEFAULT_DIAGNOSTICS_PERIOD_S)
        # A thread that dies is said on /diagnostics at once, from the loop: the manager may restart
        # the server before the next period, and the ERROR would never be seen.
        self._diagnostics_now = self.create_guard_condition(self._diagnostics_on_failure)
        self.supervisor.add_listener(lambda _reason: self._diagnostics_now.trigger())
        self._metrics_http: StatusServer | None = None
        # Slow work of plugins (dc_core.worker): a finished job wakes the loop through a guard
        # condition, made with the worker (rclpy's EventsExecutor stops firing timers beside one).
        self._worker: Worker | None = None
        self._worker_done: Any = None

    def get_logger(self) -> SeverityLogger:
        """The node's logger, called from one line per severity (dc_core.logs): any helper may log
        through it at any severity. Plugin contexts get its children."""
        logger: SeverityLogger | None = self.__dict__.get("_severity_logger")
        if logger is None:
            logger = self._severity_logger = SeverityLogger(super().get_logger())
        return logger

    # -- configuration -----------------------------------------------------------------------
    def read_params_file(self) -> dict[str, dict[str, Any]]:
        """The DC sections of the parameter file for this node's namespace, with the process'
        ``--ros-args`` parameters over them; ConfigError when this server has none. This server's
        become its read-only ROS parameters (dc_core.declared_params)."""
        loaded = load_params(self.params_file, self.get_namespace(), param_sections(process_ros_args()))
        if self.get_name() not in loaded.servers:
            raise ConfigError(self.get_name(), f"no {self.get_name()} section in {self.params_file}")
        self._declared_params = declare_read_only(self, loaded.raw[self.get_name()], self._declared_params)
        return loaded.servers

    def apply_node_params(self, node: ServerNodeParams, warnings: Sequence[str]) -> None:
        """What every server does with its parsed configuration: say its warnings, beat at its period."""
        for warning in warnings:
            self.get_logger().warning(warning)
        self.set_heartbeat_period(node.heartbeat_period)
        self.set_diagnostics_period(node.diagnostics_period)
        self.record_linger_s = node.record_linger
        if node.use_sim_time and not self.get_parameter("use_sim_time").value:
            # rclpy's time source starts following /clock when the parameter changes.
            self.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
            self.get_logger().info("use_sim_time: following /clock")

    # -- plugins -----------------------------------------------------------------------------
    def plugin_context(self, name: str) -> ServerPluginContext:
        """The context a plugin instance named ``name`` gets (dc_core.plugin.PluginContext)."""
        return ServerPluginContext(name, self.get_logger().get_child(name), self)

    @property
    def worker(self) -> Worker:
        """The server's worker threads, started on first use and stopped by :meth:`stop_worker`."""
        if self._worker is None:
            if self._worker_done is None:
                self._worker_done = self.create_guard_condition(self._run_finished_work)
            self._worker = Worker(f"{self.get_name()}-worker", self._worker_done.trigger, supervisor=self.supervisor)
        return self._worker

    def wait_worker_idle(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s until no job of the worker runs (True at once without a worker)."""
        return self._worker is None or self._worker.wait_idle(timeout)

    @property
    def worker_jobs_running(self) -> int:
        return self._worker.running if self._worker is not None else 0

    def stop_worker(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for running jobs, then stop the worker; False if some still ran."""
        worker, self._worker = self._worker, None
        if worker is None:
            return True
        idle = worker.wait_idle(timeout)
        worker.shutdown()
        return idle

    def _run_finished_work(self) -> None:
        if self._worker is not None:
            self._worker.run_finished()

    # -- metrics over HTTP -------------------------------------------------------------------
    def start_metrics_http(
        self, settings: MetricsHttpParams, document: Callable[[], dict[str, Any]], prometheus: Callable[[], str]
    ) -> None:
        """Serve ``document()`` (and its Prometheus text) while active, when ``settings.http_server``
        is on; healthy while active and no thread of the server died (``threads`` in the document)."""
        if not settings.http_server:
            return
        self._metrics_http = start_status_server(
            self.get_logger(),
            settings.http_listen,
            settings.http_port,
            health=lambda: self.lifecycle_state == "active" and not self.supervisor.unhealthy,
            metrics=lambda: {**document(), "threads": self.supervisor.metrics()},
            prometheus=lambda: prometheus() + self.supervisor.prometheus(),
            supervisor=self.supervisor,
            announce_as=self.metrics_announce_as(),
        )

    def metrics_announce_as(self) -> tuple[str, int, str]:
        """How this server's metrics address is written down for `dc status` (dc_core.metrics_registry)."""
        return self.get_name(), self.context.get_domain_id(), self.get_namespace()

    def stop_metrics_http(self) -> None:
        if self._metrics_http is not None:
            self._metrics_http.stop()
            self._metrics_http = None

    @property
    def http_address(self) -> tuple[str, int] | None:
        """Where the metrics HTTP server listens (None when it does not run)."""
        return self._metrics_http.address if self._metrics_http is not None else None

    def create_steady_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """A timer on the steady clock, for the server's own housekeeping: it keeps its period under
        use_sim_time, where the node's timers follow simulated time (and stop with it)."""
        return self.create_timer(period_s, callback, clock=self._steady_clock)

    # -- heartbeat ---------------------------------------------------------------------------
    def _send_heartbeat(self) -> None:
        msg = Heartbeat()
        msg.stamp = self.get_clock().now().to_msg()
        msg.node_name = self.get_fully_qualified_name()
        self._heartbeat_seq += 1
        msg.sequence = self._heartbeat_seq
        msg.state = HEARTBEAT_STATE_UNHEALTHY if self.supervisor.unhealthy else self._state_machine.current_state[0]
        self._heartbeat_pub.publish(msg)

    def set_heartbeat_period(self, period: float) -> None:
        self._heartbeat_timer.cancel()
        self.destroy_timer(self._heartbeat_timer)
        self._heartbeat_timer = self.create_timer(period, self._send_heartbeat, clock=self._steady_clock)

    # -- /diagnostics (dc_core.diagnostics) ---------------------------------------------------------
    def set_diagnostics_period(self, period: float) -> None:
        """Publish on /diagnostics every ``period`` seconds (0: not at all)."""
        if self._diagnostics_timer is not None:
            self._diagnostics_timer.cancel()
            self.destroy_timer(self._diagnostics_timer)
            self._diagnostics_timer = None
        if period > 0:
            self._diagnostics_timer = self.create_timer(period, self.publish_diagnostics, clock=self._steady_clock)

    def _diagnostics_on_failure(self) -> None:
        if self._diagnostics_timer is not None:  # diagnostics_period 0: not at all
            self.publish_diagnostics()

    def publish_diagnostics(self) -> None:
        statuses = [self._server_status(), *self.diagnostic_statuses()]
        self._diagnostics_pub.publish(diagnostic_array(statuses, self.get_clock().now().to_msg()))

    def _server_status(self) -> Any:
        state = self.lifecycle_state
        reason = self.supervisor.unhealthy_reason or self.unhealthy_reason()
        if reason:
            level, message = ERROR, scrub(reason)
        elif state != "active":
            level, message = WARN, f"not active: {state}"
        else:
            level, message = OK, "active"
        values = {
            "state": state,
            "namespace": self.get_namespace(),
            "thread_failures": self.supervisor.thread_failures,
            "unhealthy": scrub(reason or ""),
        }
        return diagnostic_status(f"{self.get_name()}: server", level, message, values)

    def unhealthy_reason(self) -> str:
        """Why the server is unhealthy beyond a thread that died (a subclass knows more), or ""."""
        return ""

    def diagnostic_statuses(self) -> list[Any]:
        """The server's statuses besides its own (the destination server's: one per destination)."""
        return []

    @property
    def lifecycle_state(self) -> str:
        label: str = self._state_machine.current_state[1]
        return label

    # -- transitions -------------------------------------------------------------------------
    def configure_server(self) -> None:
        raise NotImplementedError

    def activate_server(self) -> None:
        raise NotImplementedError

    def deactivate_server(self) -> None:
        raise NotImplementedError

    def cleanup_server(self) -> None:
        raise NotImplementedError

    def _guard(self, what: str, step: Any, undo: Any = None) -> TransitionCallbackReturn:
        """``step``, FAILURE if it raises and ``undo`` (a teardown) then ran to its end, ERROR if not."""
        started = time.monotonic()
        try:
            step()
        except Exception as exc:  # a plugin bug must fail the transition, not the process
            self._log_failure(what, exc)
        else:
            self.get_logger().debug(f"{what} done in {time.monotonic() - started:.3f} s")
            return TransitionCallbackReturn.SUCCESS
        if undo is not None and self._teardown(f"undoing {what}", undo) == TransitionCallbackReturn.ERROR:
            return TransitionCallbackReturn.ERROR
        return TransitionCallbackReturn.FAILURE

    def _teardown(self, what: str, step: Any) -> TransitionCallbackReturn:
        """A teardown: SUCCESS when it went to its end (a :class:`PartialTeardown` logged at ERROR),
        ERROR when it stopped part-way — the node is then neither what it was nor what it was to become."""
        started = time.monotonic()
        try:
            step()
        except PartialTeardown as exc:
            self.get_logger().error(f"{what}: done, but {exc}")
        except Exception as exc:
            self._log_failure(what, exc)
            self.get_logger().error(
                f"{what} stopped part-way: the transition ends in ERROR (on_error releases the rest)"
            )
            return TransitionCallbackReturn.ERROR
        self.get_logger().debug(f"{what} done in {time.monotonic() - started:.3f} s")
        return TransitionCallbackReturn.SUCCESS

    def _log_failure(self, what: str, exc: Exception) -> None:
        if isinstance(exc, DcError):
            self.get_logger().error(f"{what} failed: {exc}")
        else:
            self.get_logger().error(f"{what} failed: {exc!r}\n{traceback.format_exc()}")

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._guard("configure", self.configure_server, self.cleanup_server)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = self._guard("activate", self.activate_server, self.deactivate_server)
        if result == TransitionCallbackReturn.SUCCESS:
            return super().on_activate(state)
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = self._teardown("deactivate", self.deactivate_server)
        super().on_deactivate(state)  # the lifecycle publishers stop in any case
        return result

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._teardown("cleanup", self.cleanup_server)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """After a transition from ``state`` ended in ERROR: release everything (cleanup). SUCCESS
        takes the node to ``unconfigured``, FAILURE to ``finalized`` (rclpy's lifecycle)."""
        # After a failed configure whose undo stopped part-way, that undo was the cleanup: tried once more.
        result = self._teardown(f"cleanup after the failed transition from {state.label}", self.cleanup_server)
        if result == TransitionCallbackReturn.SUCCESS:
            self.get_logger().error(f"{self.get_name()} is unconfigured after an error; it must be configured again")
            return TransitionCallbackReturn.SUCCESS
        self.get_logger().fatal(
            f"{self.get_name()} is finalized: it cannot go on; only a restart of its process brings it back"
        )
        return TransitionCallbackReturn.FAILURE

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if state.label == "active":
            self._teardown("deactivate", self.deactivate_server)
        if state.label in ("active", "inactive"):
            self._teardown("cleanup", self.cleanup_server)
        return TransitionCallbackReturn.SUCCESS


def init_server_process(log_level: str, namespace: str = "", more_ros_args: Sequence[str] = ()) -> StopRequest:
    """rclpy for a process of servers, and the stop SIGINT and SIGTERM ask: its loop stops, its servers shut
    down. Give it to :func:`dc_core.signals.wake_on_signals` too, so that waiting threads see it at once."""
    use_private_umask()  # records, buffers and logs are this user's alone (dc_core.private_files)
    python_only_stdout()  # Fast DDS's own lines to stderr, not among the records (dc_core.native_stdout)
    ros_args = ["--ros-args", "--log-level", log_level]
    if namespace.strip("/"):
        ros_args += ["-r", f"__ns:={ros_namespace(namespace)}"]
    set_process_ros_args(more_ros_args)  # the servers read -p and --params-file at each configure
    # rclpy's own handlers would shut the context down under the servers before they could stop in order.
    rclpy.init(args=[*ros_args, *more_ros_args], signal_handler_options=SignalHandlerOptions.NO)
    # The handler only sets a flag and writes the wake-up socket: safe however many signals come (dc_core.signals).
    stop = StopRequest()
    stop.install()
    return stop


def run_server(node_class: type[ManagedServer], argv: Sequence[str] | None = None) -> int:
    """Process entry point of a server: ``python -m <module> PARAMS [--autostart] [--ros-args ...]``."""
    parser = argparse.ArgumentParser(prog=node_class.__name__)
    parser.add_argument("params_file")
    parser.add_argument("--log-level", default=os.environ.get("DC_LOG_LEVEL", "info"))
    parser.add_argument("--autostart", action="store_true", help="configure and activate without a manager")
    parser.add_argument("--namespace", default="", help="ROS namespace of the node")
    parser.add_argument("--use-sim-time", action="store_true", help="follow /clock (a bag, a simulator)")
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(own)

    sim_time = ["-p", "use_sim_time:=true"] if args.use_sim_time else []
    stop = init_server_process(args.log_level, args.namespace, [*sim_time, *ros_args])
    node = node_class(args.params_file)  # type: ignore[call-arg]
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    loop = ServerLoop(executor, node.intake)
    wake_on_signals(loop.wake, stop, node.supervisor)
    try:
        if args.autostart:
            if node.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                return 1
            if node.trigger_activate() != TransitionCallbackReturn.SUCCESS:
                return 1
        loop.run(stop, node.get_logger())
        state = node.lifecycle_state
        if state in ("active", "inactive", "unconfigured"):
            node.trigger_shutdown()
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        if rclpy.utilities.ok():
            rclpy.shutdown()
        sys.stdout.flush()
    return 0


class ServerLoop:
    """A server's main loop: records through its intake while it has subscriptions, the rest through the executor.

    It sleeps until something needs it — a record, a request, a due timer, a finished job, a signal
    (:meth:`wake`) — and no fixed-period turn wakes it meanwhile: an idle robot pays for nothing
    but its timers. ``idle_wait_s`` only bounds how long a wait may last.
    """

    def __init__(
        self, executor: Executor, intakes: Intake | Sequence[Intake], idle_wait_s: float = IDLE_WAIT_S
    ) -> None:
        # Several intakes when one loop serves several servers (dc-bringup --single-process).
        self.intakes = (intakes,) if isinstance(intakes, Intake) else tuple(intakes)
        self.executor = executor
        self.idle_wait_s = idle_wait_s
        # A guard condition with a callback: rclpy's executor returns from spin_once only for work to
        # do (executor.wake() alone makes it wait again for the rest of the timeout).
        self._wake = self.intakes[0].node.create_guard_condition(_nothing)

    def wake(self) -> None:
        """Make the current wait return (thread-safe): the loop then looks at its stop event."""
        self._wake.trigger()

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Handle what is ready, waiting up to ``timeout_sec`` (``idle_wait_s``) for something to be."""
        timeout = self.idle_wait_s if timeout_sec is None else timeout_sec
        first, *others = self.intakes
        if not any(intake.active for intake in self.intakes):
            self.executor.spin_once(timeout_sec=timeout)
            return
        wake = first.take_or_notice(timeout, self.executor.get_nodes(), others)
        if wake.executor_work:
            run_ready_callbacks(self.executor, EXECUTOR_TURN_MAX_CALLBACKS)
        elif wake.records and not wake.more_queued:
            # Records only, and none left queued: let the next ones gather (record_linger). At
            # 1,000 records/s one wake-up then takes dozens instead of one; per record, the wait
            # set, and the interpreter's caches going cold while it sleeps between records, cost
            # more than handling the record (docs/performance.md). The next wait returns at once
            # if anything, a record or the executor's work, came meanwhile.
            linger = min(_record_linger(intake.node) for intake in self.intakes)
            if linger > 0:
                time.sleep(linger)

    def run(self, stop: StopFlag, logger: Any) -> None:
        """Spin until ``stop`` is set or the context shuts down; a failing callback is logged, not fatal."""
        while not stop.is_set():
            try:
                self.spin_once()
            except (KeyboardInterrupt, ExternalShutdownException):
                break
            except Exception as exc:  # keep serving: one bad callback must not stop collection
                logger.error(f"callback failed: {exc!r}\n{traceback.format_exc()}")


def _record_linger(node: Any) -> float:
    return float(getattr(node, "record_linger_s", DEFAULT_RECORD_LINGER_S))


def _nothing() -> None:
    """The wake guard's callback: being run is what makes the executor's wait return."""


def run_ready_callbacks(executor: Executor, limit: int) -> int:
    """Run callbacks that are ready, without waiting, until none is or ``limit`` ran; returns how many ran.

    rclpy's executor takes one message per subscription per wait, so passes are repeated while the
    last one found work: a subscription of the node's own (a plugin's, say) is not held to one
    message per turn.
    """
    ran = 0
    ran_in_pass = 0
    while ran < limit:
        try:
            handler = executor.wait_for_ready_callbacks(timeout_sec=0.0)[0]
        except TimeoutException:  # the end of one pass over the wait set
            if ran_in_pass == 0:
                break
            ran_in_pass = 0
            continue
        except (ShutdownException, ConditionReachedException):
            break
        ran += 1
        ran_in_pass += 1
        handler()
        exception = handler.exception()
        if exception is not None:
            raise exception
    return ran
