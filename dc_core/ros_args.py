"""``--ros-args``: what DC's commands take after it, forward to every server, and read themselves.

rclpy reads these arguments for the nodes (remaps, log levels, and its own parameters such as
``use_sim_time``), but DC's settings are not rclpy's declared parameters: DC reads ``-p`` and
``--params-file`` itself (:func:`param_sections`) and merges them over its parameter file, in
their command-line order, as rcl would for a node that declared them.
"""

from __future__ import annotations

from collections.abc import Sequence

import yaml

from dc_core.config import ParamSection, nest_dotted_keys, read_sections
from dc_core.errors import ConfigError
from dc_core.topics import resolve_topic

ROS_ARGS_FLAG = "--ros-args"
ROS_ARGS_END = "--"
_WITH_VALUE = {"-r", "--remap", "-p", "--param", "--params-file", "--log-level", "--log-file-name", "-e", "--enclave"}
_ALONE = {
    f"--{switch}-{what}-logs" for switch in ("enable", "disable") for what in ("rosout", "stdout", "external-lib")
}

# The ROS arguments of this process' servers (set by dc_core.lifecycle.init_server_process): their
# nodes read -p and --params-file from them at each configure.
_process_ros_args: list[str] = []


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(the command's own arguments, the ROS arguments): each ``--ros-args`` block runs to ``--`` or the end."""
    own: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == ROS_ARGS_FLAG:
            inside = True
        elif inside and arg == ROS_ARGS_END:
            inside = False
        elif inside:
            ros.append(arg)
        else:
            own.append(arg)
    return own, ros


def check_ros_args(ros_args: Sequence[str]) -> None:
    """A ConfigError for what rcl would refuse (and the server processes with it): unknown flags, missing values."""
    _flags(ros_args)


def _flags(ros_args: Sequence[str]) -> list[tuple[str, str]]:
    """Each flag with its value ("" for a switch); ConfigError for what rcl would refuse."""
    flags = []
    i = 0
    while i < len(ros_args):
        flag = ros_args[i]
        if flag in _ALONE:
            flags.append((flag, ""))
            i += 1
            continue
        if flag not in _WITH_VALUE:
            raise ConfigError("--ros-args", f"unknown ROS argument {flag!r}")
        if i + 1 >= len(ros_args):
            raise ConfigError("--ros-args", f"{flag} needs a value")
        value = ros_args[i + 1]
        if flag in ("-r", "--remap", "-p", "--param") and ":=" not in value:
            raise ConfigError("--ros-args", f"{flag} {value!r}: expected NAME:=VALUE")
        flags.append((flag, value))
        i += 2
    return flags


def param_sections(ros_args: Sequence[str]) -> list[ParamSection]:
    """The parameters ``-p`` and ``--params-file`` give, in command-line order, as rcl keys them.

    ``-p name:=value`` is for every node (``/**``), ``-p node:name:=value`` for the node of that name;
    the value is YAML, as rcl reads it. A ``--params-file`` is read as rcl reads it (no bare names).
    """
    sections: list[ParamSection] = []
    for flag, value in _flags(ros_args):
        if flag in ("-p", "--param"):
            rule, _, text = value.partition(":=")
            node, _, name = rule.rpartition(":")
            try:
                parsed = yaml.safe_load(text) if text else ""
            except yaml.YAMLError as exc:
                raise ConfigError("--ros-args", f"-p {value!r}: the value is not YAML ({exc})") from exc
            pattern = "/" + node.strip("/") if node else "/**"
            sections.append(ParamSection(pattern, nest_dotted_keys({name: parsed}), f"--ros-args -p {rule}"))
        elif flag == "--params-file":
            sections.extend(read_sections(value, dc_file=False))
    return sections


def namespace_remap(ros_args: Sequence[str]) -> str | None:
    """The namespace ``-r __ns:=/x`` (or ``-r node:__ns:=/x`` — taken for every server) sets, if any."""
    try:
        flags = _flags(ros_args)
    except ConfigError:
        return None  # said by check_ros_args, with the rest of the configuration's checks
    for flag, value in flags:
        if flag in ("-r", "--remap"):
            rule, _, target = value.partition(":=")
            if rule.rpartition(":")[2] == "__ns":
                return target
    return None


def topic_remaps(ros_args: Sequence[str], namespace: str, node: str) -> dict[str, str]:
    """The names ``-r`` rules send elsewhere for node ``node`` in ``namespace``, fully qualified, from -> to.

    A rule's names resolve in the node's namespace, as rcl resolves them; the first rule matching a
    name wins, as in rcl; ``node:from:=to`` applies to that node only.
    """
    try:
        flags = _flags(ros_args)
    except ConfigError:
        return {}  # said by check_ros_args
    remaps: dict[str, str] = {}
    for flag, value in flags:
        if flag in ("-r", "--remap"):
            rule, _, target = value.partition(":=")
            only_for, _, source = rule.rpartition(":")
            if source.startswith("__") or (only_for and only_for != node):
                continue  # __ns, __node: not a topic
            remaps.setdefault(resolve_topic(source, namespace, node), resolve_topic(target, namespace, node))
    return remaps


def set_process_ros_args(ros_args: Sequence[str]) -> None:
    """Remember the ROS arguments this process' servers were started with."""
    _process_ros_args[:] = list(ros_args)


def process_ros_args() -> list[str]:
    """The ROS arguments of this process' servers (empty for a node built without dc_core.lifecycle)."""
    return list(_process_ros_args)
