"""The lifecycle manager: ordered configure/activate, heartbeats, restart of what died."""

from __future__ import annotations

import time
from typing import Any

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from dc_bringup.processes import ServerProcess
from dc_core.lifecycle import HEARTBEAT_QOS, HEARTBEAT_TOPIC
from dc_interfaces.msg import Heartbeat

NODE_NAME = "lifecycle_manager_dc"
# get_state answers at once from a live process: a probe unanswered this long was lost.
GET_STATE_PROBE_S = 0.5


class LifecycleManager(Node):
    def __init__(self, servers: list[ServerProcess], bond_timeout: float, service_timeout: float = 30.0) -> None:
        super().__init__(NODE_NAME)
        self.servers = servers
        self.bond_timeout = bond_timeout
        self.service_timeout = service_timeout
        self.executor_ = SingleThreadedExecutor()
        self.executor_.add_node(self)
        self._last_heartbeat: dict[str, float] = {}
        self._watch_since: dict[str, float] = {}
        self._lifecycle_clients: dict[str, tuple[Any, Any]] = {}
        self.restarts: dict[str, int] = {s.name: 0 for s in servers}
        self.create_subscription(Heartbeat, HEARTBEAT_TOPIC, self._on_heartbeat, HEARTBEAT_QOS)

    def _on_heartbeat(self, msg: Any) -> None:
        self._last_heartbeat[msg.node_name] = time.monotonic()

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
                self.create_client(ChangeState, f"/{server}/change_state"),
                self.create_client(GetState, f"/{server}/get_state"),
            )
        return self._lifecycle_clients[server]

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

    def _wait_ready(self, proc: ServerProcess, started: float) -> bool:
        """The new process sent a heartbeat and answers on its lifecycle services."""
        deadline = time.monotonic() + self.service_timeout
        while self._last_heartbeat.get(proc.name, 0.0) < started:
            if not proc.running() or time.monotonic() > deadline:
                return False
            self.spin_for(0.05)
        self._forget_clients(proc.name)
        change, get = self._client(proc.name)
        while time.monotonic() < deadline:
            if not proc.running():
                return False
            if change.service_is_ready() and get.service_is_ready():
                break
            self.spin_for(0.05)
        # "Ready" only says the graph knows a server of that name, and a killed process stays in the
        # graph until its DDS lease ends (~20 s): a request sent before the new process' endpoints
        # are matched is lost, and its transition waited service_timeout / attempts (seen in CI
        # after SIGSTOP + restart). Only the new process can answer get_state; ask it until it does.
        while time.monotonic() < deadline:
            if not proc.running():
                return False
            if self._call(get, GetState.Request(), GET_STATE_PROBE_S) is not None:
                return True
        return False

    def transition(self, server: str, label: str, target: str, attempts: int = 3) -> bool:
        """Send a transition by label (an id sent to a wrong state kills rclpy's service; see notes).

        A request lost in transit is retried; the state is checked first so a transition that did
        happen is never sent twice.
        """
        for _ in range(attempts):
            change, _ = self._client(server)
            request = ChangeState.Request()
            request.transition = Transition(label=label)
            response = self._call(change, request, self.service_timeout / attempts)
            if response is not None:
                return bool(response.success)
            if self.state(server) == target:
                return True
            self.get_logger().warning(f"{server}: no answer to {label}; asking again")
        return False

    def state(self, server: str) -> str | None:
        _, get = self._client(server)
        response = self._call(get, GetState.Request(), 5.0)
        return None if response is None else str(response.current_state.label)

    def bring_up(self, proc: ServerProcess, started: float) -> bool:
        log = self.get_logger()
        if not self._wait_ready(proc, started):
            log.error(f"{proc.name} did not come up (exit code {proc.exit_code()})")
            return False
        for label, target in (("configure", "inactive"), ("activate", "active")):
            if not self.transition(proc.name, label, target):
                log.error(f"{proc.name}: {label} failed (see its log above)")
                return False
        self._watch_since[proc.name] = time.monotonic()
        log.info(f"{proc.name} active (pid {proc.pid})")
        return True

    def start_all(self) -> bool:
        for proc in self.servers:
            started = time.monotonic()
            proc.start()
            if not self.bring_up(proc, started):
                return False
        return True

    def check_bonds(self) -> None:
        """Restart a server whose process died or whose heartbeat stopped for bond_timeout."""
        now = time.monotonic()
        for proc in self.servers:
            reason = None
            if not proc.running():
                reason = f"exited with code {proc.exit_code()}"
            else:
                last = max(self._last_heartbeat.get(proc.name, 0.0), self._watch_since.get(proc.name, now))
                if now - last > self.bond_timeout:
                    reason = f"no heartbeat for {now - last:.1f} s (bond_timeout {self.bond_timeout} s)"
            if reason is None:
                continue
            self.get_logger().fatal(f"{proc.name} {reason}: restarting it")
            proc.kill()
            self._last_heartbeat.pop(proc.name, None)
            self.restarts[proc.name] += 1
            started = time.monotonic()
            proc.start()
            if not self.bring_up(proc, started):
                self.get_logger().error(f"{proc.name} could not be restarted; will try again")
                self._watch_since[proc.name] = time.monotonic()

    def shut_down(self, timeout: float) -> None:
        """Reverse order: measurements stop first, destinations flush last."""
        for proc in reversed(self.servers):
            if proc.running():
                code = proc.stop(timeout)
                self.get_logger().info(f"{proc.name} stopped (exit code {code})")
