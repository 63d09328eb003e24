"""A real mosquitto broker on a loopback port for the MQTT destination's tests, and a subscriber.

The broker runs from a temporary configuration (no persistence, its log in a file of the test's
folder); ``start`` polls until the port accepts connections, ``stop`` sends TERM then
KILL. It can be stopped and started again on the same port, which is how the tests make an outage.
"""

from __future__ import annotations

import getpass
import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path
from types import TracebackType
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from tests.http_receiver import free_port

MOSQUITTO = "/usr/sbin/mosquitto"
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd")


def missing_reason() -> str | None:
    """Why the broker cannot run here (for pytest.skip), or None."""
    if not os.access(MOSQUITTO, os.X_OK):
        return f"{MOSQUITTO} is not installed (Debian package mosquitto)"
    return None


class Broker:
    """mosquitto on 127.0.0.1:``port``; ``users`` (name → password) turns anonymous access off.

    ``tls``: (certificate, key) PEM files make the listener a TLS one; ``client_ca``: it then asks
    every client for a certificate signed by that CA.
    ``persistent``: the broker saves its sessions when stopped and loads them when started again,
    so a subscriber's subscription and the QoS 1 messages queued for it survive a restart.
    """

    def __init__(
        self,
        folder: Path,
        port: int | None = None,
        *,
        users: dict[str, str] | None = None,
        persistent: bool = False,
        tls: tuple[Path, Path] | None = None,
        client_ca: Path | None = None,
    ) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.config = folder / "mosquitto.conf"
        self.log = folder / "mosquitto.log"
        lines = [
            f"listener {self.port} 127.0.0.1",
            *(["persistence true", f"persistence_location {folder}/"] if persistent else ["persistence false"]),
            f"log_dest file {self.log}",  # stdout into a file would be block-buffered
            "log_type all",
            # As root mosquitto switches to the user `mosquitto`, who cannot read the test's
            # folder; staying the user that runs the tests keeps the password file readable.
            f"user {getpass.getuser()}",
        ]
        if tls is not None:
            lines += [f"certfile {tls[0]}", f"keyfile {tls[1]}"]
            if client_ca is not None:
                lines += [f"cafile {client_ca}", "require_certificate true"]
        if users:
            if MOSQUITTO_PASSWD is None:
                raise RuntimeError("mosquitto_passwd is not installed")
            password_file = folder / "passwords"
            password_file.write_text("")
            for name, password in users.items():
                subprocess.run([MOSQUITTO_PASSWD, "-b", str(password_file), name, password], check=True)
            lines += ["allow_anonymous false", f"password_file {password_file}"]
        else:
            lines.append("allow_anonymous true")
        self.config.write_text("\n".join(lines) + "\n")
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 10.0) -> Broker:
        self.process = subprocess.Popen(
            [MOSQUITTO, "-c", str(self.config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            stdin=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + timeout
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"mosquitto exited with {self.process.returncode}:\n{self.log_text()}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return self
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(
                        f"mosquitto not listening on {self.port} after {timeout} s:\n{self.log_text()}"
                    ) from None
                time.sleep(0.02)

    def stop(self, timeout: float = 5.0) -> None:
        process, self.process = self.process, None
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def log_text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


class Subscriber:
    """A paho client subscribed to ``topic`` (wildcards allowed) that keeps every message.

    It reconnects by itself (paho's default), every second, so it survives broker restarts.
    With ``client_id`` its session is persistent (clean_session false): against a ``persistent``
    broker, what the destination publishes before this client is back is kept for it, not lost.
    """

    def __init__(self, port: int, topic: str = "#", *, qos: int = 2, client_id: str = "") -> None:
        self.port = port
        self.topic = topic
        self.qos = qos
        self.messages: list[mqtt.MQTTMessage] = []
        self._changed = threading.Condition()
        self._subscribed = threading.Event()
        self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=not client_id, protocol=mqtt.MQTTv311
        )
        self.client.reconnect_delay_set(1, 1)
        self.client.on_connect = self._on_connect
        self.client.on_subscribe = self._on_subscribe
        self.client.on_message = self._on_message

    def _on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if not reason.is_failure:
            client.subscribe(self.topic, qos=self.qos)

    def _on_subscribe(self, client: Any, userdata: Any, mid: int, reasons: Any, properties: Any) -> None:
        self._subscribed.set()

    def _on_message(self, client: Any, userdata: Any, message: mqtt.MQTTMessage) -> None:
        with self._changed:
            self.messages.append(message)
            self._changed.notify_all()

    def __enter__(self) -> Subscriber:
        self.client.connect("127.0.0.1", self.port)
        self.client.loop_start()
        if not self._subscribed.wait(10):
            raise RuntimeError(f"no SUBACK from the broker on {self.port}")
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.client.disconnect()
        self.client.loop_stop()

    def records(self) -> list[dict[str, Any]]:
        with self._changed:
            return [json.loads(m.payload) for m in self.messages]

    def wait_for(self, count: int, timeout: float = 10.0) -> list[mqtt.MQTTMessage]:
        """At least ``count`` messages, or AssertionError after ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while len(self.messages) < count:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"{len(self.messages)} of {count} messages after {timeout} s")
                self._changed.wait(left)
            return list(self.messages)
