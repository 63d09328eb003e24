"""``dc demo``: the QR-code storage demo and the dashboard, from one command.

What docs/demos.md and docs/dashboard.md do in four terminals, in one process: the local PostgreSQL
and S3 servers (:mod:`dc_bringup.local_servers`), the simulated robot (``dc sim``), ``dc-bringup``
with params/demos/tb3_qrcodes_minio_pgsql.yaml and its destination server's metrics on, and
``dc dashboard`` over what they store. So that every page of the dashboard shows real data, the
demo's copy of that file also collects what the original's demo did not (distance traveled, CPU,
memory, into the same table), and the dashboard's indexes are built once DC has created its tables.
The children write to log files under the state folder, not to the terminal. A child that exits
stops the demo; Ctrl-C, SIGTERM or ``--duration`` stops everything in the reverse order of the
start, each child with a bounded wait, then SIGKILL.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from dc_bringup.local_servers import LocalServer, ServerError
from dc_bringup.local_servers.processes import free_port, log_tail, port_free
from dc_bringup.local_servers.run import DEFAULT_PORTS, environment, environment_lines, make_server
from dc_bringup.processes import die_with_parent
from dc_core.errors import DcError
from dc_core.signals import stop_on_signals
from dc_dashboard import settings as dashboard_settings

# The demo files live in the checkout, beside the packages (an editable install, as `make install` does).
DEMO_PARAMS = Path(__file__).resolve().parents[1] / "params" / "demos" / "tb3_qrcodes_minio_pgsql.yaml"
SERVERS = ("postgres", "s3")  # what the demo delivers to; InfluxDB would only cost start time
# Measurements added to the demo file for the dashboard's Overview (distance) and System (CPU, memory) pages.
DASHBOARD_MEASUREMENTS: dict[str, dict[str, Any]] = {
    "distance_traveled": {
        "plugin": "dc_measurements/DistanceTraveled",
        "polling_interval": 2000,
        "global_frame": "odom",
        "robot_base_frame": "base_link",
    },
    "cpu": {"plugin": "dc_measurements/Cpu", "polling_interval": 5000},
    "memory": {"plugin": "dc_measurements/Memory", "polling_interval": 5000},
}
# Seconds a child gets after SIGINT before SIGKILL. dc-bringup stops its three servers one after
# the other, the destination server delivering what it holds for up to flb.grace.
STOP_TIMEOUT_S = {"dashboard": 5.0, "dc-bringup": 45.0, "sim": 10.0}
INDEX_RETRY_S = 3.0
"""How often the demo looks whether DC has made the tables the dashboard's indexes go on."""


class DemoError(DcError):
    """The demo cannot go on: a server did not start, a child exited."""


@dataclass(frozen=True)
class DemoOptions:
    port: int = 8088
    duration: float | None = None
    state_dir: Path = Path("var/dc/demo")
    rate: float = 1.0


@dataclass
class Child:
    name: str
    process: subprocess.Popen[bytes]
    log: Path


class Demo:
    """Starts the servers and the children, watches them until ``stop``, then stops them all."""

    def __init__(self, options: DemoOptions, stop: threading.Event, say: Callable[[str], Any] | None = None) -> None:
        self.options = options
        self.stop = stop
        self.say = say or _say
        self.state_dir = options.state_dir.absolute()
        self.servers: list[LocalServer] = []
        self.children: list[Child] = []

    def run(self) -> int:
        try:
            self._run()
            return 0
        except DemoError as exc:
            self.say(f"dc demo: {exc}")
            return 1
        finally:
            self._stop_all()

    def _run(self) -> None:
        deadline = time.monotonic() + self.options.duration if self.options.duration else math.inf
        if not DEMO_PARAMS.is_file():
            raise DemoError(f"{DEMO_PARAMS} not found: dc demo runs from a checkout of DC (make install)")
        self.state_dir.mkdir(parents=True, exist_ok=True)
        self.say(
            f"dc demo: logs in {self.state_dir}/ (sim.log, dc-bringup.log, dashboard.log; the servers' under servers/)"
        )
        env = self._environment(self._start_servers())
        if self.stop.is_set():
            return
        metrics_port = free_port()
        params = self._params_with_metrics(metrics_port)
        python = sys.executable
        # The robot waits for DC's subscribers, so the first shelf it stops at is recorded; --loop:
        # it drives its round until stopped, as a robot at work does.
        self._start(
            "sim",
            [python, "-m", "dc_bringup.cli", "sim", "--clock", "--loop", "--rate", f"{self.options.rate:g}",
             "--wait-subscribers", "60"],
            env,
        )  # fmt: skip
        self._start("dc-bringup", [python, "-m", "dc_bringup.launcher", str(params), "--use-sim-time"], env)
        self._start(
            "dashboard",
            [python, "-m", "dc_bringup.cli", "dashboard", "--port", str(self.options.port),
             "--metrics", f"http://127.0.0.1:{metrics_port}/api/v1/metrics"],
            env,
        )  # fmt: skip
        url = f"http://127.0.0.1:{self.options.port}/"
        announced = indexed = False
        postgres = dashboard_settings.from_sources(None, env).postgres
        index_at = time.monotonic()
        while not self.stop.wait(0.5):
            self._check()
            if not indexed and time.monotonic() >= index_at:
                # A connection each time: asked every few seconds, not at the loop's pace.
                indexed = self._index_tables(postgres)
                index_at = time.monotonic() + INDEX_RETRY_S
            if not announced and _answers(url):
                announced = True
                self.say(
                    f"dc demo: open {url} : Overview draws the robot's path over the warehouse map, Camera each"
                    " shelf's QR codes and image (the first within a minute), Health the delivery; Ctrl-C stops it all"
                )
            if time.monotonic() >= deadline:
                self.say(f"dc demo: {self.options.duration:g} s passed (--duration)")
                return

    def _start_servers(self) -> dict[str, dict[str, Any]]:
        folder = self.state_dir / "servers"
        for name in SERVERS:
            if self.stop.is_set():
                break
            server = make_server(name, folder, DEFAULT_PORTS[name])
            if server.running():  # left by a demo that was killed: the password it was given is gone with it
                self.say(f"dc demo: stopping the {name} server an earlier dc demo left running")
                server.stop()
            if not port_free(server.port):  # `make servers` runs, say: the demo does not need the usual port
                server = make_server(name, folder, free_port())
            try:
                server.start()
            except ServerError as exc:
                raise DemoError(f"the {name} server did not start: {exc}") from None
            self.servers.append(server)
        settings = {server.name: server.settings() for server in self.servers}
        # For psql and the other commands of docs/demos.md while the demo runs; it holds the passwords.
        env_file = folder / "servers.env"
        env_file.touch(mode=0o600)
        env_file.chmod(0o600)
        env_file.write_text(environment_lines(settings))
        return settings

    def _environment(self, settings: dict[str, dict[str, Any]]) -> dict[str, str]:
        env = {**os.environ, **environment(settings)}
        # A demo on a laptop should not talk to the robots of the network; the user's ROS_DOMAIN_ID is kept.
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        env.setdefault("ROS_LOG_DIR", str(self.state_dir / "ros-log"))
        env["PYTHONUNBUFFERED"] = "1"  # the log files follow the children as they go
        return env

    def _params_with_metrics(self, port: int) -> Path:
        """The demo file with the destination server's HTTP server on (the dashboard's health page reads
        it) and :data:`DASHBOARD_MEASUREMENTS` stored in PostgreSQL."""
        params = yaml.safe_load(DEMO_PARAMS.read_text())
        flb = params["destination_server"]["ros__parameters"]["flb"]
        flb.update(http_server=True, http_listen="127.0.0.1", http_port=port)
        measurements = params["measurement_server"]["ros__parameters"]
        pgsql = params["destination_server"]["ros__parameters"]["flb_pgsql"]
        for name, section in DASHBOARD_MEASUREMENTS.items():
            topic = f"/dc/measurement/{name}"
            measurements["measurement_plugins"].append(name)
            measurements[name] = {
                **section,
                "group_key": name,
                "topic_output": topic,
                "tags": ["flb_pgsql"],
                "include_measurement_name": True,
            }
            pgsql["inputs"].append(topic)
        path = self.state_dir / DEMO_PARAMS.name
        path.write_text(yaml.safe_dump(params, sort_keys=False))
        return path

    def _index_tables(self, postgres: Any) -> bool:
        """True once DC's two tables exist with the dashboard's indexes (built here, when both exist: a
        demo of DC's own shows no missing-index banner)."""
        import psycopg

        from dc_dashboard import indexes

        try:
            with psycopg.connect(**postgres.connect_kwargs(), autocommit=True) as connection:
                both = connection.execute(
                    "SELECT to_regclass(%s) IS NOT NULL AND to_regclass(%s) IS NOT NULL",
                    (postgres.table, postgres.files_table),
                ).fetchone()
        except psycopg.Error:
            return False
        if not (both and both[0]):
            return False
        built = indexes.create(postgres, say=lambda line: None) == 0
        if built:
            self.say("dc demo: the dashboard's indexes are built")
        return built

    def _start(self, name: str, command: list[str], env: dict[str, str]) -> None:
        log = self.state_dir / f"{name}.log"
        with log.open("wb") as out:
            # Own process group: a terminal's Ctrl-C reaches dc demo only, which stops the children in order.
            process = subprocess.Popen(
                command,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                env=env,
                preexec_fn=die_with_parent,
                process_group=0,
            )
        self.children.append(Child(name, process, log))

    def _check(self) -> None:
        for child in self.children:
            code = child.process.poll()
            if code is not None:
                raise DemoError(f"{child.name} exited with code {code}, stopping the demo{log_tail(child.log)}")
        for server in self.servers:
            if not server.running():
                raise DemoError(f"the {server.name} server stopped (its log is in {server.state_dir})")

    def _stop_all(self) -> None:
        for child in reversed(self.children):
            _stop_child(child, STOP_TIMEOUT_S[child.name], self.say)
        for server in reversed(self.servers):
            server.stop()
        if self.children or self.servers:
            self.say("dc demo: stopped")


def _say(line: str) -> None:
    print(line, flush=True)  # at once, also when a pipe or a file reads it


def _stop_child(child: Child, timeout: float, say: Callable[[str], Any]) -> None:
    if child.process.poll() is not None:
        return
    # SIGINT: what each of them takes as Ctrl-C, ending in order with exit code 0.
    child.process.send_signal(signal.SIGINT)
    try:
        child.process.wait(timeout)
    except subprocess.TimeoutExpired:
        say(f"dc demo: {child.name} did not stop within {timeout:g} s: killed")
        child.process.kill()
        child.process.wait()


def _answers(url: str) -> bool:
    with contextlib.suppress(OSError), urllib.request.urlopen(url + "favicon.ico", timeout=2):
        return True
    return False


def main(args: Any) -> int:
    stop = stop_on_signals()  # handlers that take no lock (dc_core.signals)
    options = DemoOptions(port=args.port, duration=args.duration, state_dir=Path(args.state_dir), rate=args.rate)
    return Demo(options, stop).run()
