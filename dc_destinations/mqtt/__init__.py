"""MQTT destination: each record published as one message to a broker, on a topic made from the record.

MQTT is how many fleets move telemetry, so a robot can hand its records to the broker the rest of
the fleet already reads. A record counts as delivered only when the broker acknowledges it (PUBACK
for QoS 1, PUBCOMP for QoS 2); until then it stays in DC's buffer, which does the retrying. The
plugin therefore keeps no queue of its own: paho's automatic reconnection is off, and a connection
lost or never made is reported to the buffer as a retryable failure, then made again by the next
``send``.
"""

from __future__ import annotations

import hashlib
import socket
import ssl
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

try:
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
except ImportError as exc:  # an optional dependency: say which extra brings it
    raise ImportError(f"the MQTT destination needs paho-mqtt: pip install 'ros2-dc[mqtt]' ({exc})") from exc

from dc_core.destination import (
    ConfigurationProblem,
    Destination,
    OutgoingRecord,
    ProbeResult,
    RetryableError,
    SendOutcome,
)
from dc_core.errors import ConfigError
from dc_core.params import host_param, param, port_problem, url_host
from dc_core.records import MalformedRecord
from dc_destinations.connection import Connection
from dc_destinations.templates import fill_template
from dc_destinations.templates import template_keys as shared_template_keys
from dc_destinations.tls import TlsParams, client_context, warn_if_credentials_in_clear

# MQTT topic names are UTF-8 strings of at most 65535 bytes, and a published one has no wildcard.
_TOPIC_MAX_BYTES = 65535
_WILDCARDS = ("+", "#", "\0")
_NO_WILDCARDS = "a topic without the wildcards '+' and '#'"
# CONNACK reasons that mean the credentials (or their rights) are wrong, not the network.
_AUTH_REASONS = ("not authorized", "bad user name or password", "bad username or password")
# How often a waiting send looks again at the acknowledgements, besides being woken by them.
_WAIT_SLICE_S = 0.05


def template_keys(template: str) -> list[str]:
    """The record keys a topic template names (``"dc/{robot}/{name}"`` → robot, name); ValueError saying
    what was expected (dc_destinations.templates), a wildcard included."""
    return shared_template_keys(template, forbidden="".join(_WILDCARDS), forbidden_problem=_NO_WILDCARDS)


def _topic_problem(template: str) -> str | None:
    if not template:
        return "a topic template, like dc/{name}"
    try:
        template_keys(template)
    except ValueError as exc:
        return str(exc)
    return None


@dataclass(frozen=True, kw_only=True, repr=False)
class MqttParams(TlsParams):
    host: str = host_param("the MQTT broker")
    port: int = param(1883, check=port_problem, doc="TCP port of the broker (8883 is usual with `tls`)")
    topic: str = param(
        "dc/{name}", check=_topic_problem, doc="Topic of each record; {key} is replaced by the record's value of key"
    )
    qos: int = param(
        1, choices=(0, 1, 2), doc="MQTT quality of service: 0 at most once, 1 at least once, 2 exactly once"
    )
    retain: bool = param(False, doc="Ask the broker to keep the last message of each topic for new subscribers")
    client_id: str = param(
        "", doc="MQTT client identifier; empty: one derived from this machine, the destination and host"
    )
    clean_session: bool = param(True, doc="Start a new session at each connection (false: the broker keeps it)")
    username: str = param("", doc="User name sent to the broker; empty: none")
    password: str = param("", secret=True, doc="Password sent to the broker, with `username` (never logged)")
    keepalive: int = param(60, minimum=5, maximum=65535, doc="Seconds between keep-alive pings on an idle connection")
    connect_timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds to connect and receive CONNACK")
    publish_timeout: float = param(
        30.0, minimum=0.1, maximum=3600, doc="Seconds to wait for the broker to acknowledge a batch"
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.password and not self.username:
            raise ConfigError("password", "set username too (MQTT sends a password only with a user name)")


def default_client_id(destination: str, host: str, machine: str | None = None) -> str:
    """A client id that stays the same across restarts (so a ``clean_session: false`` session resumes)
    and differs between robots: two clients with one id keep pushing each other off the broker.

    23 characters of [0-9a-z-], the length every MQTT 3.1.1 broker must accept.
    """
    machine = socket.gethostname() if machine is None else machine
    digest = hashlib.sha256(f"{machine}\0{destination}\0{host}".encode()).hexdigest()
    return "dc-" + digest[:20]


class _Connection:
    """One paho client and its network thread, for as long as one TCP connection lasts.

    A new connection gets a new client: what the old one still held unacknowledged is in DC's
    buffer anyway, and will be sent again from there.
    """

    def __init__(self, client: mqtt.Client) -> None:
        self.client = client
        self.changed = threading.Condition()
        self.connack: Any = None  # the CONNACK reason code once it arrived
        self.connected = False
        self.session_present = False
        self.lost: str | None = None  # why the connection ended, once it has

    def on_connect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        with self.changed:
            self.connack = reason
            self.session_present = bool(flags.session_present)
            self.connected = not reason.is_failure
            self.changed.notify_all()

    def on_disconnect(self, client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        with self.changed:
            self.connected = False
            self.lost = str(reason) if reason is not None else "connection closed"
            self.changed.notify_all()

    def on_publish(self, client: Any, userdata: Any, mid: int, reason: Any, properties: Any) -> None:
        with self.changed:
            self.changed.notify_all()

    def close(self) -> None:
        """Say goodbye if still connected, and stop the network thread."""
        # Returns an error code, not raising, when the socket is gone already.
        self.client.disconnect()
        self.client.loop_stop()
        with self.changed:
            self.connected = False


class Mqtt(Destination[MqttParams]):
    """Publish each record as a JSON message to an MQTT broker, on a topic made from the record."""

    def __init__(self, context: Any, params: MqttParams) -> None:
        super().__init__(context, params)
        self._keys = template_keys(params.topic)
        self._tls: ssl.SSLContext | None = None
        # Opened again once paho says it is lost (connected False).
        self._connection = self.keep(
            Connection(
                "", self._connect, _Connection.close, timeout=params.connect_timeout, usable=lambda c: c.connected
            )
        )
        self.client_id = ""
        self.address = ""

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        host = url_host(p.host)
        self.address = self._connection.where = f"{'mqtts' if p.tls_on else 'mqtt'}://{host}:{p.port}"
        self._connection.secrets = [p.password, p.tls_key_passwd]
        self.client_id = p.client_id or default_client_id(self.context.name, p.host)
        self._tls = client_context(p, f"destination_server.{self.context.name}", self.context.logger)
        warn_if_credentials_in_clear(
            self.context.logger,
            self.context.name,
            p.host,
            credentials=f"the password of {p.username}" if p.password else "",
            verified_tls=p.tls_verified,
            fix="set tls: true with tls_verify: true (tls_ca_file for a private CA; port 8883 is usual)",
        )

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a broker that is down
        # must not hold up activation.
        p = self.params
        self.context.logger.info(f"publishing to {self.address} on {p.topic!r} with QoS {p.qos}")

    def probe(self) -> ProbeResult:
        """An MQTT CONNECT with the real credentials (and TLS), then a DISCONNECT; nothing published.
        On a connection of its own, under a client id of its own with a clean session: the running
        DC's, taken over, would be disconnected by the broker, and a kept session would be left behind."""
        self._connect(client_id=f"{self.client_id}-check", clean_session=True).close()
        p = self.params
        return ProbeResult(True, f"connected to {self.address}" + (f" as {p.username}" if p.username else ""))

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        outcome = SendOutcome()
        messages: list[tuple[int, str, bytes]] = []
        for index, record in enumerate(batch):
            try:
                messages.append((index, self.topic_of(record), record.to_json().encode("utf-8")))
            except (ValueError, MalformedRecord) as exc:
                outcome.reject[index] = str(exc)
        if not messages:
            return outcome
        self._publish(self._connection.get(), messages, outcome)
        return outcome if outcome.retry or outcome.reject else None

    def topic_of(self, record: OutgoingRecord) -> str:
        """The record's topic; ValueError saying why when the record cannot have one."""
        topic = fill_template(self.params.topic, self._keys, record.data, "topic")
        if any(w in topic for w in _WILDCARDS):
            raise ValueError(f"topic {topic!r} holds a wildcard ('+', '#') or a NUL, which MQTT forbids in a publish")
        if topic.startswith("$"):
            raise ValueError(f"topic {topic!r} starts with '$', which brokers keep for themselves")
        if len(topic.encode("utf-8")) > _TOPIC_MAX_BYTES:
            raise ValueError(f"topic is longer than MQTT's {_TOPIC_MAX_BYTES} bytes")
        return topic

    def _publish(self, connection: _Connection, messages: list[tuple[int, str, bytes]], outcome: SendOutcome) -> None:
        p = self.params
        sent: list[tuple[int, mqtt.MQTTMessageInfo]] = []
        for index, topic, payload in messages:
            try:
                info = connection.client.publish(topic, payload, qos=p.qos, retain=p.retain)
            except ValueError as exc:  # paho's own checks (payload over 256 MB)
                outcome.reject[index] = f"not publishable: {exc}"
                continue
            if info.rc not in (MQTTErrorCode.MQTT_ERR_SUCCESS, MQTTErrorCode.MQTT_ERR_AGAIN):
                outcome.retry[index] = self._scrub(f"not published to {self.address}: {mqtt.error_string(info.rc)}")
                continue
            sent.append((index, info))
        deadline = time.monotonic() + p.publish_timeout
        with connection.changed:
            while True:
                waiting = [(index, info) for index, info in sent if not _acknowledged(info)]
                left = deadline - time.monotonic()
                if not waiting or not connection.connected or left <= 0:
                    break
                connection.changed.wait(min(left, _WAIT_SLICE_S))
            lost = connection.lost
        if not waiting:
            return
        if lost is not None or not connection.connected:
            reason = f"connection to {self.address} lost before the broker acknowledged: {lost or 'closed'}"
            if len(waiting) == len(messages) and not outcome.reject:
                self._connection.close()
                raise RetryableError(self._scrub(reason))
        else:
            reason = f"no acknowledgement from {self.address} within {p.publish_timeout:g} s"
        # A broker that does not acknowledge in time, or a broken connection: start afresh next
        # time, so paho does not pile up the messages that DC's buffer will send again anyway.
        self._connection.close()
        for index, _info in waiting:
            outcome.retry[index] = self._scrub(reason)

    # -- connection --------------------------------------------------------------------------------
    def _connect(self, *, client_id: str | None = None, clean_session: bool | None = None) -> _Connection:
        """A connected client; ``client_id`` and ``clean_session`` other than the parameters' for the probe."""
        p = self.params
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=self.client_id if client_id is None else client_id,
            clean_session=p.clean_session if clean_session is None else clean_session,
            protocol=mqtt.MQTTv311,
            reconnect_on_failure=False,  # DC's buffer retries, with its backoff
        )
        connection = _Connection(client)
        client.on_connect = connection.on_connect
        client.on_disconnect = connection.on_disconnect
        client.on_publish = connection.on_publish
        client.connect_timeout = p.connect_timeout
        if p.username:
            client.username_pw_set(p.username, p.password or None)
        if self._tls is not None:
            client.tls_set_context(self._tls)
        try:
            client.connect(p.host, p.port, keepalive=p.keepalive)
        except (OSError, ValueError) as exc:
            raise RetryableError(self._connection.failure("cannot connect to MQTT broker", exc)) from None
        client.loop_start()
        deadline = time.monotonic() + p.connect_timeout
        with connection.changed:
            while connection.connack is None and connection.lost is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                connection.changed.wait(left)
            connack, lost = connection.connack, connection.lost
        if connack is None or connack.is_failure:
            connection.close()
            message = self._scrub(self._refusal(connack, lost))
            if connack is not None and str(connack).lower() in _AUTH_REASONS:
                raise ConfigurationProblem(message, fix="check username and password, and the broker's ACL")
            raise RetryableError(message)
        resumed = " (session resumed)" if connection.session_present else ""
        self.context.logger.info(f"connected to {self.address} as client {self.client_id!r}{resumed}")
        return connection

    def _refusal(self, connack: Any, lost: str | None) -> str:
        p = self.params
        if connack is None:
            why = f"connection closed: {lost}" if lost else f"no CONNACK within {p.connect_timeout:g} s"
            return f"MQTT broker {self.address} did not accept the connection: {why}"
        reason = str(connack)
        message = f"MQTT broker {self.address} refused the connection: {reason}"
        if reason.lower() in _AUTH_REASONS:
            who = f"user {p.username!r}" if p.username else "no user name"
            message += f" (check `username` and `password`; sent {who})"
        return message

    def _scrub(self, text: str) -> str:
        """The passwords masked, should a library or broker ever quote them."""
        return self._connection.scrub(text)


def _acknowledged(info: mqtt.MQTTMessageInfo) -> bool:
    try:
        return info.is_published()
    except (ValueError, RuntimeError):  # paho says it was never sent; not acknowledged then
        return False
