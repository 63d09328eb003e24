"""DC's health on ROS's own channel: ``/diagnostics`` (diagnostic_msgs/DiagnosticArray), docs/diagnostics.md.

rqt_robot_monitor, Foxglove and a diagnostic aggregator read ``/diagnostics``: there DC shows beside the
robot's other components without anyone running `dc status`. Every server publishes one status about
itself (``<node>: server``) and what it adds of its own (the destination server one per destination,
``destination_server: <destination>``), named as ROS 2's diagnostic_updater names its tasks: the node's
name without namespace, a colon, the task.

The topic is absolute, as diagnostic_updater's (and so Nav2's) is: an aggregator listens on ``/diagnostics``
and nowhere else, so a DC started in a namespace publishes there too, and says its namespace in the
``namespace`` key. Nothing published here is secret: texts pass through :func:`scrub`.
"""

from __future__ import annotations

import dataclasses
import re
import socket
from collections.abc import Iterable
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import QoSProfile, ReliabilityPolicy

DIAGNOSTICS_TOPIC = "/diagnostics"
# diagnostic_updater's depth: a late status is worth nothing once the next one is out.
DIAGNOSTICS_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
# A monitor shows one line per status: a longer text is cut, its whole is in the logs.
TEXT_LIMIT = 300

# Credentials an error text may carry even where the destination did not echo its own secret: a URL's
# user information, and key=value pairs whose key names a secret.
_URL_CREDENTIALS = re.compile(r"(?<=://)[^/\s@:]*:[^/\s@]*@")
_SECRET_PAIRS = re.compile(r"(?i)\b(password|passwd|pwd|secret|token|api_key|apikey|access_key)(\s*[=:]\s*)[^\s,;&]+")


def scrub(text: str, secrets: Iterable[str] = ()) -> str:
    """``text`` on one line without ``secrets`` (replaced by ``***``) nor credentials recognisable by form."""
    for secret in sorted(secrets, key=len, reverse=True):
        if secret:
            text = text.replace(secret, "***")
    text = _URL_CREDENTIALS.sub("***@", text)
    text = _SECRET_PAIRS.sub(lambda m: f"{m.group(1)}{m.group(2)}***", text)
    text = " ".join(text.split())
    return text if len(text) <= TEXT_LIMIT else text[: TEXT_LIMIT - 1] + "…"


def secret_values(params: Any) -> list[str]:
    """The values of the fields declared ``secret`` (dc_core.params.param) of a parsed parameter
    dataclass, nested ones included: what :func:`scrub` masks in that plugin's errors."""
    found: list[str] = []
    if not dataclasses.is_dataclass(params) or isinstance(params, type):
        return found
    for f in dataclasses.fields(params):
        value = getattr(params, f.name, None)
        if f.metadata.get("secret") and isinstance(value, str) and value:
            found.append(value)
        elif dataclasses.is_dataclass(value):
            found.extend(secret_values(value))
    return found


def status(name: str, level: int, message: str, values: dict[str, Any]) -> DiagnosticStatus:
    """One status: ``values`` as key-values, None shown as an empty value, floats to the millisecond."""
    msg = DiagnosticStatus()
    msg.level = level
    msg.name = name
    msg.message = message
    msg.hardware_id = hardware_id()
    msg.values = [KeyValue(key=key, value=_text(value)) for key, value in values.items()]
    return msg


def array(statuses: list[DiagnosticStatus], stamp: Any) -> DiagnosticArray:
    msg = DiagnosticArray()
    msg.header.stamp = stamp
    msg.status = statuses
    return msg


_HOST: list[str] = []


def hardware_id() -> str:
    """The host's name: a monitor of several robots tells them apart by it (ROS leaves it to the driver)."""
    if not _HOST:
        _HOST.append(socket.gethostname())
    return _HOST[0]


def _text(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.3f}".rstrip("0").rstrip(".") if value == value else "nan"
    return str(value)
