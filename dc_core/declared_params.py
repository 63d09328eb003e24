"""DC's settings as read-only ROS parameters of its nodes, for ``ros2 param list/get/describe``.

DC reads its parameter file itself, at each configure (dc_core.config), so a value set through the
parameter services would change nothing: the parameters are declared read-only, as what the server
runs with. Nested sections are flattened to dotted names (``flb.grace``), as ROS parameter files
write them. A value no ROS parameter type holds — null, an empty or mixed list, a list of mappings
— is declared as its JSON text. Secrets are never served: a key that names one (a password, a
token, a webhook) is declared with the value ``(secret)``, and ``${NAME}`` references are shown as
written, not expanded.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

# Keys whose values are credentials (the plugins' secret=True parameters are all named so).
_SECRET_KEY = re.compile(r"passw|secret|token|webhook|credential", re.IGNORECASE)
SECRET_SHOWN_AS = "(secret)"
_INT64 = range(-(2**63), 2**63)
JSON_NOTE = "JSON text: no ROS parameter type holds this value"
# rclpy's and the time source's own parameters: declared by rclpy, not by DC.
_ROS_OWN = ("use_sim_time", "start_type_description_service", "qos_overrides.")


def flatten(params: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"flb": {"grace": 5}}`` -> ``{"flb.grace": 5}`` (an empty section declares nothing)."""
    flat: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten(value, name + "."))
        elif not isinstance(value, Mapping):
            flat[name] = _redacted(str(key), value)
    return flat


def _redacted(key: str, value: Any) -> Any:
    """``value`` with the values of secret keys replaced, in lists of mappings too."""
    if _SECRET_KEY.search(key) and value not in ("", None):
        return SECRET_SHOWN_AS
    if isinstance(value, list):
        return [_redacted(key, item) for item in value]
    if isinstance(value, Mapping):
        return {k: _redacted(str(k), v) for k, v in value.items()}
    return value


def ros_value(value: Any) -> tuple[Any, bool]:
    """(a value rclpy can hold, whether it is JSON text standing for the YAML value)."""
    if isinstance(value, bool | str) or (isinstance(value, int) and value in _INT64) or isinstance(value, float):
        return value, False
    if isinstance(value, list) and value:
        if all(isinstance(v, bool) for v in value) or all(isinstance(v, str) for v in value):
            return list(value), False
        if all(isinstance(v, int) and not isinstance(v, bool) and v in _INT64 for v in value):
            return list(value), False
        if all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            return [float(v) for v in value], False
    return json.dumps(value, default=str), True


def declare_read_only(node: Node, params: Mapping[str, Any], declared: set[str]) -> set[str]:
    """Declare (or update) ``params`` on ``node`` read-only; undeclare those of ``declared`` gone since.

    Returns the names now declared. rclpy refuses every change to a read-only parameter, its node's
    own included, once declared; DC re-reads its file at each configure, so the values are set
    through rclpy's internal setter that takes new descriptors (what ``declare_parameters`` uses).
    """
    flat = {
        name: value
        for name, value in flatten(params).items()
        if not name.startswith(_ROS_OWN) and (name in declared or not node.has_parameter(name))
    }
    parameters: list[Parameter] = []
    descriptors: dict[str, ParameterDescriptor] = {}
    for name, value in flat.items():
        held, as_json = ros_value(value)
        parameters.append(Parameter(name, value=held))
        descriptors[name] = ParameterDescriptor(
            name=name, read_only=True, dynamic_typing=True, description=JSON_NOTE if as_json else ""
        )
    for name in declared - set(flat):
        parameters.append(Parameter(name, Parameter.Type.NOT_SET))
        descriptors[name] = ParameterDescriptor(name=name, dynamic_typing=True)
    if parameters:
        result = node._set_parameters_atomically_common(parameters, descriptors)
        if not result.successful:
            node.get_logger().warning(f"DC's parameters not declared on the node: {result.reason}")
            return declared
    return set(flat)
