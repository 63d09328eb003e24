"""The lifecycle manager: ordered configure/activate, heartbeats, restart of what died, and the services
``manage_nodes`` (dc_lifecycle_interfaces/srv/ManageLifecycleNodes: startup, pause, resume, reset, shutdown) and
``is_active`` (std_srvs/srv/Trigger), as Nav2's lifecycle manager offers them.

Transitions run on the main loop only (:meth:`LifecycleManager.run_commands`). The services are
served by a node of their own on a thread of its own: a request is queued and its answer waits until
the main loop has carried it out. (Served by the manager's own executor, an async callback awaiting
the main loop made every spin of that executor resume the waiting task instead of taking messages:
the transitions' answers and the heartbeats stopped arriving.)
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future
from typing import Any

from dc_lifecycle_interfaces.msg import Heartbeat
from dc_lifecycle_interfaces.srv import ManageLifecycleNodes
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from dc_bringup import instances
from dc_bringup.processes import ManagedServerHandle
from dc_core.lifecycle import HEARTBEAT_QOS, HEARTBEAT_STATE_UNHEALTHY, HEARTBEAT_TOPIC
from dc_core.logs import SeverityLogger
from dc_core.supervision import Supervisor
from dc_destinations.health import HEALTH_QOS, HEALTH_TOPIC, degraded_line
from dc_interfaces.msg import StringStamped

NODE_NAME = "lifecycle_manager_dc"
# is_active's message when the servers are active but a destination is failing (dc_destinations.health).
DEGRADED_PREFIX = "running, degraded: "
# get_state answers at once from a live process: a probe unanswered this long was lost.
GET_STATE_PROBE_S = 0.5
# get_state of a server that is up: unanswered this long, its state cannot be read (it hangs, or it is
# busy in a transition: a server answers one request at a time).
GET_STATE_TIMEOUT_S = 5.0
# How long a transition may take before the manager asks where the server is, by default: this more
# than destination_server's flb.grace (default_transition_timeout), which a deactivate may take.
TRANSITION_TIMEOUT_S = 30.0
PROBES_PER_CLIENT = 4
# Longest wait between two attempts to restart a server that does not come up.
MAX_RETRY_DELAY_S = 60.0
# Longest a manage_nodes request waits for the main loop to carry it out.
COMMAND_TIMEOUT_S = 300.0
# How often the watch looks at the servers when nothing wakes it: heartbeats (every second each),
# commands, signals and a child's exit (SIGCHLD) do; this bounds how late a silent server is seen.
WATCH_PERIOD_S = 1.0
# The services thread sleeps until a request comes or destroy_node wakes it; this only bounds a wait.
IDLE_WAIT_S = 5.0


# What each manage_nodes command brings the servers to: (transitions in order, reversed order?, target state).
_COMMANDS = {
    ManageLifecycleNodes.Request.STARTUP: ((("configure", "inactive"), ("activate", "active")), False, "active"),
    ManageLifecycleNodes.Request.RESUME: ((("activate", "active"),), False, "active"),
    ManageLifecycleNodes.Request.PAUSE: ((("deactivate", "inactive"),), True, "inactive"),
    ManageLifecycleNodes.Request.RESET: (
        (("deactivate", "inactive"), ("cleanup", "unconfigured")),
        True,
        "unconfigured",
    ),
}
# is_active's message, after a manage_nodes command that failed: what failed (`dc lifecycle` prints it).
FAILED_PREFIX = "; last command failed: "
# Where each transition label can start from.
_SOURCE_STATE = {"configure": "unconfigured", "activate": "inactive", "deactivate": "active", "cleanup": "inactive"}


class LifecycleManager(Node):
    def __init__(
        self,
        servers: Sequence[ManagedServerHandle],
        bond_timeout: float,
        service_timeout: float = 30.0,
        namespace: str = "",
        discovery_from: float | None = None,
        transition_timeout: float = TRANSITION_TIMEOUT_S,
    ) -> None:
        """``discovery_from``: when this process joined the ROS graph (time.monotonic()), if before now.
        ``transition_timeout``: how long a transition may take before the server is asked where it is
        (:func:`default_transition_timeout`)."""
        super().__init__(NODE_NAME, namespace=namespace or None)
        self.servers = servers
        # Servers are addressed by fully qualified name: two DC instances in other namespaces share the
        # heartbeat topic and may have servers of the same name.
        ns = self.get_namespace().rstrip("/")
        self._fqn = {s.name: f"{ns}/{s.name}" for s in servers}
        # The state the servers should be in: a server restarted while paused comes back paused.
        self.target_state = "active"
        self.shutdown_requested = False
        self._commands: deque[tuple[int, Future[bool]]] = deque()
        self.bond_timeout = bond_timeout
        self.service_timeout = service_timeout
        self.transition_timeout = transition_timeout
        # A command's transitions, each up to transition_timeout and a get_state, run before its answer.
        self.command_timeout = max(COMMAND_TIMEOUT_S, 2 * len(servers) * (transition_timeout + GET_STATE_TIMEOUT_S))
        # What the last manage_nodes command failed at, one line per server (is_active tells it).
        self.command_failures: list[str] = []
        # Servers a transition left in a state they cannot go on from (its teardown stopped part-way:
        # unconfigured or finalized by on_error), with that state: restarted by the watch.
        self._errored: dict[str, str] = {}
        self.executor_ = SingleThreadedExecutor()
        self.executor_.add_node(self)
        self._wake = self.create_guard_condition(_nothing)
        self._last_heartbeat: dict[str, float] = {}
        # Servers whose heartbeat says a thread of theirs died (dc_core.supervision): restarted, after
        # an orderly stop that commits what they hold in memory (up to stop_timeout seconds).
        self._unhealthy: set[str] = set()
        self.stop_timeout = 30.0
        self._watch_since: dict[str, float] = {}
        # Servers whose last bring-up failed, with the seconds to wait before the next attempt:
        # restarted then even if their heartbeat goes on (a process that sends heartbeats but never
        # got configured would otherwise stay so), at doubling intervals (a configure that keeps
        # failing must not become a restart loop).
        self._not_up: dict[str, float] = {}
        self._lifecycle_clients: dict[str, tuple[Any, Any]] = {}
        self.restarts: dict[str, int] = {s.name: 0 for s in servers}
        # One DC per domain and namespace (dc_bringup.instances): looked for before each server's
        # first transition, the first time once discovery had DISCOVERY_S from now; the reason this
        # one stopped, if it did.
        self._discovery_from = time.monotonic() if discovery_from is None else discovery_from
        self._alone_checked = False
        self.conflict: str | None = None
        self.create_subscription(Heartbeat, HEARTBEAT_TOPIC, self._on_heartbeat, HEARTBEAT_QOS)
        # The destinations' health as destination_server last told it (dc_destinations.health).
        self._destination_health: dict[str, Any] = {}
        self.create_subscription(StringStamped, HEALTH_TOPIC, self._on_destination_health, HEALTH_QOS)
        self._server_of = {fqn: name for name, fqn in self._fqn.items()}
        self._services_node = Node(f"{NODE_NAME}_services", namespace=namespace or None, context=self.context)
        me = self.get_fully_qualified_name()
        self._services_node.create_service(ManageLifecycleNodes, f"{me}/manage_nodes", self._on_manage_nodes)
        self._services_node.create_service(Trigger, f"{me}/is_active", self._on_is_active)
        self._services_executor = SingleThreadedExecutor(context=self.context)
        self._services_executor.add_node(self._services_node)
        self._services_stop = threading.Event()
        # Guard conditions with a callback: rclpy's spin_once returns only for work to do.
        self._services_wake = self._services_node.create_guard_condition(_nothing)
        # The services thread runs under the supervision rule (dc_core.supervision); one that died is
        # started again by the watch (check_bonds), the manager being what restarts everything else.
        self.supervisor = Supervisor(self.get_logger())
        self._services_thread = self.supervisor.start_thread(self._serve, name="manager-services")

    def get_logger(self) -> SeverityLogger:
        """The node's logger, called from one line per severity (dc_core.logs)."""
        logger: SeverityLogger | None = self.__dict__.get("_severity_logger")
        if logger is None:
            logger = self._severity_logger = SeverityLogger(super().get_logger())
        return logger

    def _serve(self) -> None:
        while not self._services_stop.is_set():
            try:
                # Woken by a request, or by destroy_node: no periodic wake-up while nothing happens.
                self._services_executor.spin_once(timeout_sec=IDLE_WAIT_S)
            except Exception:
                if self._services_stop.is_set():
                    return  # the context ended under it: dc-bringup is stopping
                raise  # logged with its traceback and counted by the supervisor

    def destroy_node(self) -> None:
        # The services' thread lets go of its node before the node goes.
        self._services_stop.set()
        self._services_wake.trigger()
        self._services_thread.join(timeout=5.0)
        self._services_executor.shutdown(timeout_sec=1.0)
        self._services_node.destroy_node()
        super().destroy_node()

    def _on_heartbeat(self, msg: Any) -> None:
        name = self._server_of.get(msg.node_name)
        if name is not None:
            self._last_heartbeat[name] = time.monotonic()
            if msg.state == HEARTBEAT_STATE_UNHEALTHY and name not in self._unhealthy:
                self._unhealthy.add(name)
                self._wake.trigger()

    def _on_destination_health(self, msg: Any) -> None:
        try:
            states = json.loads(msg.data)
        except ValueError:
            return
        if isinstance(states, dict):
            self._destination_health = states

    # -- services ------------------------------------------------------------------------------
    def _on_manage_nodes(self, request: Any, response: Any) -> Any:
        """On the services thread: queue the command, answer once the main loop carried it out."""
        if request.command not in _COMMANDS and request.command != ManageLifecycleNodes.Request.SHUTDOWN:
            self.get_logger().error(f"manage_nodes: unknown command {request.command}")
            response.success = False
            return response
        done: Future[bool] = Future()
        self._commands.append((request.command, done))
        self._wake.trigger()  # the main loop carries it out now, not at its next wake-up
        try:
            response.success = done.result(timeout=self.command_timeout)
        except TimeoutError:
            response.success = False
        return response

    def _on_is_active(self, request: Any, response: Any) -> Any:
        down = sorted({*self._not_up, *self._errored})
        response.success = self.target_state == "active" and not down
        response.message = f"servers {self.target_state}" + (f"; not up: {', '.join(down)}" if down else "")
        failing = degraded_line(self._destination_health, time.time())
        if response.success and failing:
            # Still active (success stays true for Nav2-style callers); `dc lifecycle is-active` tells
            # this apart by the prefix and exits with its own code.
            response.message = f"{DEGRADED_PREFIX}{failing}"
        if self.command_failures:
            response.message += FAILED_PREFIX + "; ".join(self.command_failures)
        return response

    def run_commands(self) -> None:
        """Carry out the manage_nodes requests received (main loop only)."""
        while self._commands:
            command, done = self._commands.popleft()
            if command == ManageLifecycleNodes.Request.SHUTDOWN:
                self.get_logger().info("manage_nodes: shutdown requested")
                self.shutdown_requested = True
                done.set_result(True)
                continue
            steps, reverse, target = _COMMANDS[command]
            self.get_logger().info(f"manage_nodes: bringing every server to {target}")
            self.target_state = target
            self.command_failures = []
            done.set_result(self.bring_to(target, steps, reverse))

    def bring_to(self, target: str, steps: Any, reverse: bool) -> bool:
        """Every server to ``target``; False, with one line per server that is not there, if any is not."""
        failures = []
        for proc in reversed(self.servers) if reverse else self.servers:
            failure = self._bring(proc.name, target, steps)
            if failure is not None:
                self.get_logger().error(failure)
                failures.append(failure)
        self.command_failures = failures
        return not failures

    def _bring(self, server: str, target: str, steps: Any) -> str | None:
        current = self.state(server)
        if current is None:
            return f"{server}: its state cannot be read (no answer to get_state in {GET_STATE_TIMEOUT_S:g} s)"
        for label, to in steps:
            if current == _SOURCE_STATE[label]:
                failure = self.transition(server, label, to)
                if failure is not None:
                    if label in ("configure", "activate") and server not in self._errored:
                        # Not coming up: the watch restarts it as a server whose bring-up failed, and
                        # is_active says so meanwhile.
                        self._not_up.setdefault(server, self.bond_timeout)
                        self._watch_since[server] = time.monotonic()
                    return failure
                current = to
        if current != target:
            return f"{server} is {current}, not {target}"
        self._not_up.pop(server, None)  # up after all: no restart is due
        return None

    def _forget_clients(self, server: str) -> None:
        # A client matched with a dead process' service may send its request there only: a restarted
        # server gets fresh clients.
        clients = self._lifecycle_clients.pop(server, None)
        if clients is not None:
            for client in clients:
                self.destroy_client(client)

    def _client(self, server: str) -> tuple[Any, Any]:
        if server not in self._lifecycle_clients:
            self._lifecycle_clients[server] = (
                self.create_client(ChangeState, f"{self._fqn[server]}/change_state"),
                self.create_client(GetState, f"{self._fqn[server]}/get_state"),
            )
        return self._lifecycle_clients[server]

    def wait_for_work(self, timeout: float = WATCH_PERIOD_S) -> None:
        """Handle one callback (a heartbeat, an answer); return when woken (command, signal) or after ``timeout``."""
        self.executor_.spin_once(timeout_sec=timeout)

    def wake(self) -> None:
        """Make :meth:`wait_for_work` return (thread-safe)."""
        self._wake.trigger()

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self.executor_.spin_once(timeout_sec=min(left, 0.1))

    def _call(self, client: Any, request: Any, timeout: float) -> Any:
        future = client.call_async(request)
        self.executor_.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            client.remove_pending_request(future)
            return None
        return future.result()

    def _not_ready(self, proc: ManagedServerHandle, started: float) -> str | None:
        """None once the new process sent a heartbeat and answers on its lifecycle services, else why not."""
        deadline = time.monotonic() + self.service_timeout
        while self._last_heartbeat.get(proc.name, 0.0) < started:
            if not proc.running():
                return f"exited with code {proc.exit_code()}"
            if time.monotonic() > deadline:
                return f"sent no heartbeat in {self.service_timeout:g} s"
            self.spin_for(0.05)
        self._forget_clients(proc.name)
        change, get = self._client(proc.name)
        while not (change.service_is_ready() and get.service_is_ready()):
            if not proc.running():
                return f"exited with code {proc.exit_code()}"
            if time.monotonic() > deadline:
                return f"its lifecycle services were not discovered in {self.service_timeout:g} s"
            self.spin_for(0.05)
        # "Ready" only says the graph knows a server of that name, and a killed process stays in the
        # graph until its DDS lease ends (~20 s): a request sent before the new process' endpoints
        # are matched is lost, and its transition waited service_timeout / attempts (seen after
        # SIGSTOP + restart). Only the new process can answer get_state; ask it until it does, with
        # fresh clients now and then in case the ones we have were matched with the dead process only.
        probes = 0
        while True:
            if not proc.running():
                return f"exited with code {proc.exit_code()}"
            if time.monotonic() > deadline:
                return f"did not answer get_state in {self.service_timeout:g} s ({probes} requests)"
            if self._call(get, GetState.Request(), GET_STATE_PROBE_S) is not None:
                if probes:
                    self.get_logger().info(f"{proc.name} answered get_state after {probes} unanswered requests")
                return None
            probes += 1
            if probes % PROBES_PER_CLIENT == 0:
                self._forget_clients(proc.name)
                change, get = self._client(proc.name)

    # -- one DC per domain and namespace -------------------------------------------------------------
    def _own_pids(self) -> set[int]:
        return {os.getpid()} | {pid for s in self.servers if (pid := s.pid) is not None}

    def _seen_nodes(self) -> list[instances.SeenNode]:
        names = instances.dc_node_names(NODE_NAME)
        return instances.seen_nodes(self, self.get_namespace(), names, self._own_pids())

    def another_instance(self) -> list[instances.SeenNode]:
        """The nodes of another DC in this domain and namespace, graph discovery given DISCOVERY_S
        from this manager's start (and, once one is seen, a little more for the others of that DC —
        each of its processes is discovered on its own — longer while its manager is not among them)."""
        own_names = {NODE_NAME: 1, f"{NODE_NAME}_services": 1}
        first_seen: float | None = None
        while True:
            # In the loop: a server started meanwhile is ours too.
            own_names.update({s.name: 1 for s in self.servers if s.running()})
            found = instances.others(self._seen_nodes(), own_names)
            now = time.monotonic()
            if found and first_seen is None:
                first_seen = now
            if first_seen is None:
                if now - self._discovery_from >= instances.DISCOVERY_S:
                    return found
            elif now - first_seen >= instances.MANAGER_WAIT_S or (
                now - first_seen >= instances.MORE_NODES_S and any(n.name == NODE_NAME for n in found)
            ):
                return found
            self.spin_for(0.05)

    def _check_alone(self) -> bool:
        """Before each server's first transition: False, and the one line said, when another DC is there.

        Looked at for every server of the first bring-up, not for the first alone: the window
        (DISCOVERY_S) only says that no other DC was seen by then, and one discovered later while
        this one starts (a loaded machine) stops it alike, before any of its transitions could reach
        that DC's servers. A look after the window costs one read of the graph.
        """
        if self._alone_checked:
            return True
        found = self.another_instance()
        if found:
            self.conflict = instances.refusal(found, self.context.get_domain_id(), self.get_namespace())
            self.get_logger().error(self.conflict)
            return False
        return True

    def transition(self, server: str, label: str, target: str, attempts: int = 3) -> str | None:
        """Send a transition by label (an id sent to a wrong state kills rclpy's service; see notes);
        None once the server is in ``target``, else one line saying where it is and why.

        Each wait is ``transition_timeout``: a server answers one request at a time, so one that is
        still in the transition does not answer get_state either, and is not asked again (a
        transition sent twice fails the second time). A server that answers get_state in the
        state the transition starts from never received it: sent again. A transition that ended in
        another state (on_error after a teardown that stopped part-way: unconfigured or finalized)
        makes the watch restart the server. Never sent while a node of that name runs in another
        process than this DC's: the request would reach it too.
        """
        strangers = [n for n in instances.others(self._seen_nodes()) if n.name == server]
        if strangers:
            return (
                f"not sending {label} to {server}: "
                + ", ".join(n.describe() for n in strangers)
                + " is another DC's, and would receive it too"
            )
        source = _SOURCE_STATE[label]
        for _ in range(attempts):
            change, _ = self._client(server)
            request = ChangeState.Request()
            request.transition = Transition(label=label)
            response = self._call(change, request, self.transition_timeout)
            if response is not None:
                self._answered(server)
                if response.success:
                    return None
            state = self.state(server)
            if state == target:  # done by an earlier request whose answer was lost
                return None
            if state is None:
                asked = "failed" if response is not None else f"did not finish in {self.transition_timeout:g} s"
                return (
                    f"{server}: {label} {asked} and get_state is unanswered for {GET_STATE_TIMEOUT_S:g} s: "
                    "it hangs (restarted once its heartbeat is missing for bond_timeout)"
                )
            if state != source:
                self._errored[server] = state
                self._wake.trigger()
                return f"{server}: {label} failed part-way and left it {state} (its log above says why): restarting it"
            if response is not None:
                return f"{server}: {label} failed; it is still {state} (its log above says why)"
            self.get_logger().warning(f"{server}: {label} not received (still {state}); sending it again")
        return f"{server}: {label} not received in {attempts} attempts"

    def state(self, server: str) -> str | None:
        """The server's lifecycle state; None when it does not answer get_state in GET_STATE_TIMEOUT_S."""
        _, get = self._client(server)
        response = self._call(get, GetState.Request(), GET_STATE_TIMEOUT_S)
        if response is None:
            return None
        self._answered(server)
        return str(response.current_state.label)

    def _answered(self, server: str) -> None:
        # A server sends no heartbeat while in a transition (it does one thing at a time): one that
        # answers is alive, and the watch counts its silence from now (a deactivate may take
        # flb.grace seconds, longer than bond_timeout). One being restarted keeps its own schedule.
        if server not in self._not_up:
            self._watch_since[server] = time.monotonic()

    def bring_up(self, proc: ManagedServerHandle, started: float) -> bool:
        log = self.get_logger()
        reason = self._not_ready(proc, started)
        if reason is not None:
            log.error(f"{proc.name} did not come up: {reason}")
            return False
        if not self._check_alone():
            return False
        steps = (("configure", "inactive"), ("activate", "active"))
        for label, target in steps[: {"unconfigured": 0, "inactive": 1}.get(self.target_state, 2)]:
            failure = self.transition(proc.name, label, target)
            if failure is not None:
                log.error(failure)
                return False
        self._watch_since[proc.name] = time.monotonic()
        log.info(f"{proc.name} {self.target_state} (pid {proc.pid})")
        return True

    def start_all(self) -> bool:
        for proc in self.servers:
            started = time.monotonic()
            proc.start()
            if not self.bring_up(proc, started):
                return False
        self._alone_checked = True
        return True

    def check_bonds(self) -> None:
        """Restart a server whose process died, whose heartbeat stopped for bond_timeout or says it is
        unhealthy; and the manager's services thread if it died."""
        if not self._services_thread.is_alive() and not self._services_stop.is_set():
            self.get_logger().error("lifecycle services thread restarted")
            self._services_thread = self.supervisor.start_thread(self._serve, name="manager-services")
        now = time.monotonic()
        for proc in self.servers:
            reason = None
            if not proc.running():
                reason = f"exited with code {proc.exit_code()}"
            elif proc.name in self._not_up:
                if now - self._watch_since[proc.name] < self._not_up[proc.name]:
                    continue
                reason = "did not come up"
            elif proc.name in self._unhealthy:
                reason = "reports itself unhealthy (a thread of it died; its log above says which and why)"
            elif proc.name in self._errored:
                reason = f"is {self._errored[proc.name]} after a failed transition (its log above says why)"
            else:
                last = max(self._last_heartbeat.get(proc.name, 0.0), self._watch_since.get(proc.name, now))
                if now - last > self.bond_timeout:
                    reason = f"no heartbeat for {now - last:.1f} s (bond_timeout {self.bond_timeout} s)"
            if reason is None:
                continue
            self.get_logger().fatal(f"{proc.name} {reason}: restarting it")
            if proc.name in self._unhealthy or proc.name in self._errored:
                # Stopped in order: it commits the records it holds in memory before it goes.
                proc.stop(self.stop_timeout)
            else:
                proc.kill()
            self._unhealthy.discard(proc.name)
            self._errored.pop(proc.name, None)
            self._last_heartbeat.pop(proc.name, None)
            self.restarts[proc.name] += 1
            started = time.monotonic()
            proc.start()
            if self.bring_up(proc, started):
                self._not_up.pop(proc.name, None)
                # A heartbeat the old process sent before it stopped is not the new one's word.
                self._unhealthy.discard(proc.name)
            else:
                previous = self._not_up.get(proc.name)
                delay = min(2 * previous, MAX_RETRY_DELAY_S) if previous else self.bond_timeout
                self._not_up[proc.name] = delay
                self._watch_since[proc.name] = time.monotonic()
                self.get_logger().error(f"{proc.name} could not be restarted; trying again in {delay:g} s")

    def shut_down(self, timeout: float) -> None:
        """Reverse order: measurements stop first, destinations flush last."""
        for proc in reversed(self.servers):
            if proc.running():
                code = proc.stop(timeout)
                self.get_logger().info(f"{proc.name} stopped (exit code {code})")


def default_transition_timeout(configs: dict[str, Any]) -> float:
    """destination_server's flb.grace and TRANSITION_TIMEOUT_S: a deactivate delivers for up to
    flb.grace seconds, and must not be thought lost meanwhile (TRANSITION_TIMEOUT_S alone without a
    destination_server). ``configs``: the parsed sections (dc_bringup.validate.ValidationReport.configs)."""
    destinations = configs.get("destination_server")
    grace = float(destinations.node.flb.grace) if destinations is not None else 0.0
    return grace + TRANSITION_TIMEOUT_S


def _nothing() -> None:
    """A wake guard's callback: being run is what makes spin_once return."""
