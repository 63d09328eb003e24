"""dc_interfaces and dc_lifecycle_interfaces: the message contract, and a real publish/subscribe through rclpy.

dc_interfaces shares its name with the original C++ DC's package, so it holds exactly the original's
types: a workspace that overlays the original package (or a node built against it) must see the same
types, with the same type hashes (Jazzy's RIHS01, which endpoints compare). DC's own types
(Heartbeat, ManageLifecycleNodes) are in dc_lifecycle_interfaces.
"""

from __future__ import annotations

import json
import os
import re
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import rclpy
from dc_lifecycle_interfaces.msg import Heartbeat
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from dc_interfaces.msg import Barcode, Condition, FlushEvent, StringStamped
from tests.domains import fresh_domain_id

REPO = Path(__file__).resolve().parent.parent

TIMEOUT_S = 10.0


@pytest.mark.parametrize(
    ("message_type", "expected"),
    [
        (StringStamped, {"header": "std_msgs/Header", "data": "string", "group_key": "string"}),
        (Condition, {"data": "boolean"}),
        (
            Barcode,
            {
                "data": "string",
                "type": "string",
                "top": "uint16",
                "left": "uint16",
                "width": "uint16",
                "height": "uint16",
            },
        ),
        (FlushEvent, {"incident_id": "string", "stamp": "builtin_interfaces/Time"}),
        (
            Heartbeat,
            {
                "stamp": "builtin_interfaces/Time",
                "node_name": "string",
                "sequence": "uint64",
                "state": "uint8",
            },
        ),
    ],
    ids=["StringStamped", "Condition", "Barcode", "FlushEvent", "Heartbeat"],
)
def test_message_fields(message_type: Any, expected: dict[str, str]) -> None:
    # Order matters too: it is the serialization order on the wire.
    assert list(message_type.get_fields_and_field_types().items()) == list(expected.items())


def test_message_defaults_and_ranges() -> None:
    heartbeat = Heartbeat()
    assert (heartbeat.node_name, heartbeat.sequence, heartbeat.state) == ("", 0, 0)
    # Field checks are off by default in Jazzy (ROS_PYTHON_CHECK_FIELDS); ask for them.
    heartbeat = Heartbeat(check_fields=True)
    heartbeat.sequence = 2**64 - 1
    heartbeat.state = 255
    with pytest.raises(AssertionError):
        heartbeat.state = 256
    assert Condition().data is False
    assert Condition(data=True).data is True


def test_string_stamped_roundtrip() -> None:
    context = Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())
    try:
        node = rclpy.create_node("dc_interfaces_roundtrip", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            qos = 10  # KEEP_LAST 10, reliable, volatile
            received: list[StringStamped] = []
            node.create_subscription(StringStamped, "dc_test/string_stamped", received.append, qos)
            publisher = node.create_publisher(StringStamped, "dc_test/string_stamped", qos)

            deadline = time.monotonic() + TIMEOUT_S
            while publisher.get_subscription_count() < 1:
                assert time.monotonic() < deadline, "subscription never matched the publisher"
                executor.spin_once(timeout_sec=0.05)

            sent = StringStamped()
            sent.header.stamp.sec = 1_700_000_000
            sent.header.stamp.nanosec = 123_456_789
            sent.header.frame_id = "base_link"
            sent.data = '{"uptime": 42, "name": "caf\\u00e9 ✓"}'
            sent.group_key = "robot_group"
            publisher.publish(sent)

            while not received:
                assert time.monotonic() < deadline, "message not received before the deadline"
                executor.spin_once(timeout_sec=0.05)

            assert received == [sent]
            got = received[0]
            assert (got.header.stamp.sec, got.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
            assert got.header.frame_id == "base_link"
            assert got.data == sent.data
            assert got.group_key == "robot_group"
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


# tf2_msgs/msg/TFMessage's hash as Jazzy's tf2_msgs gives it (`ros2 topic info -v /tf` on a robot): when
# make install builds DC's copy, a different hash would make DC's /tf subscriptions miss real robots.
UPSTREAM_TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_tf_message_has_the_type_hash_of_real_robots() -> None:
    from tf2_msgs.msg import TFMessage

    context = Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())
    try:
        node = rclpy.create_node("dc_test_tf_hash", context=context)
        node.create_publisher(TFMessage, "/dc_test_tf_hash", 10)
        (endpoint,) = node.get_publishers_info_by_topic("/dc_test_tf_hash")
        assert str(endpoint.topic_type_hash) == UPSTREAM_TF_MESSAGE_HASH
        assert list(TFMessage.get_fields_and_field_types().items()) == [
            ("transforms", "sequence<geometry_msgs/TransformStamped>")
        ]
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_manage_lifecycle_nodes_is_nav2s_service() -> None:
    from dc_lifecycle_interfaces.srv import ManageLifecycleNodes

    request = ManageLifecycleNodes.Request
    assert (request.STARTUP, request.PAUSE, request.RESUME, request.RESET, request.SHUTDOWN) == (0, 1, 2, 3, 4)
    assert request.get_fields_and_field_types() == {"command": "uint8"}
    assert ManageLifecycleNodes.Response.get_fields_and_field_types() == {"success": "boolean"}


# The original DC's dc_interfaces, file for file: msg/ and srv/ of its humble branch (50336c9, the
# version docs/differences.md compares with), and FlushEvent.msg, added in its package version 0.2.0.
ORIGINAL_DC_INTERFACES = {
    "msg/StringStamped.msg": "std_msgs/Header header\n\nstring data\nstring group_key\n",
    "msg/Condition.msg": "bool data\n",
    "msg/Barcode.msg": "string data\nstring type\nuint16 top\nuint16 left\nuint16 width\nuint16 height\n",
    "msg/FlushEvent.msg": "string incident_id\nbuiltin_interfaces/Time stamp\n",
    "srv/DetectBarcode.srv": "sensor_msgs/Image frame\n---\nBarcode[] barcodes\n",
    "srv/DrawImage.srv": (
        "sensor_msgs/Image frame\nstring   shape\nuint16   box_top\nuint16   box_left\nuint16   box_height\n"
        "uint16   box_width\nuint16   box_thickness\nuint16[] color\nuint16[] polygon\nuint16   font_txt\n"
        "uint16   font_thickness\nfloat32  font_scale\nstring   text\n---\nsensor_msgs/Image frame\nbool success\n"
    ),
    "srv/SaveImage.srv": "sensor_msgs/Image frame\nstring            path\n---\nbool success\n",
}


def definition_lines(text: str) -> list[str]:
    """What defines the type: the field and separator lines, comments and blank lines aside."""
    lines = (re.sub(r"\s+", " ", line.split("#", 1)[0]).strip() for line in text.splitlines())
    return [line for line in lines if line]


def test_dc_interfaces_sources_define_the_originals_types_and_no_other() -> None:
    package = REPO / "dc_interfaces"
    ours = {str(p.relative_to(package)) for p in [*package.glob("msg/*.msg"), *package.glob("srv/*.srv")]}
    assert ours == set(ORIGINAL_DC_INTERFACES)
    for name, original in ORIGINAL_DC_INTERFACES.items():
        assert definition_lines((package / name).read_text()) == definition_lines(original), name
    cmake = (package / "CMakeLists.txt").read_text()
    assert sorted(re.findall(r'"((?:msg|srv)/\w+\.(?:msg|srv))"', cmake)) == sorted(ORIGINAL_DC_INTERFACES)


def share_directory(package: str) -> Path:
    """Where an interface package's share/ is: under a sourced ROS prefix, else the venv (`make install`)."""
    prefixes = [*filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)), sys.prefix]
    for prefix in prefixes:
        if (Path(prefix) / "share" / package / "package.xml").is_file():
            return Path(prefix) / "share" / package
    raise AssertionError(f"{package} is installed under none of {prefixes}")


def original_type_hashes(tmp_path: Path) -> dict[str, str]:
    """The RIHS01 type hashes of the original's definitions, made as rosidl makes them for a build."""
    from rosidl_adapter.msg import convert_msg_to_idl
    from rosidl_adapter.srv import convert_srv_to_idl
    from rosidl_generator_type_description import generate_type_hash

    source = tmp_path / "original" / "dc_interfaces"
    idl_tuples = []
    for name, text in ORIGINAL_DC_INTERFACES.items():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        (source / name).write_text(text)
        convert = convert_msg_to_idl if name.endswith(".msg") else convert_srv_to_idl
        idl = convert(source, "dc_interfaces", Path(name), tmp_path / "idl")
        idl_tuples.append(f"{tmp_path / 'idl'}:{idl.relative_to(tmp_path / 'idl')}")
    arguments = tmp_path / "arguments.json"
    dependencies = ["builtin_interfaces", "std_msgs", "sensor_msgs", "service_msgs"]
    arguments.write_text(
        json.dumps(
            {
                "package_name": "dc_interfaces",
                "output_dir": str(tmp_path / "hashes"),
                "idl_tuples": idl_tuples,
                "include_paths": [f"{dep}:{share_directory(dep)}" for dep in dependencies],
            }
        )
    )
    hashes = {}
    for generated in generate_type_hash(str(arguments)):
        top = json.loads(Path(generated).read_text())["type_hashes"][0]
        # A service's hash covers its request, response and event types, which get files of their own.
        if not top["type_name"].endswith(("_Request", "_Response", "_Event")):
            hashes[top["type_name"]] = top["hash_string"]
    return hashes


def test_installed_dc_interfaces_has_the_type_hashes_of_the_original(tmp_path: Path) -> None:
    original = original_type_hashes(tmp_path)
    assert len(original) == len(ORIGINAL_DC_INTERFACES)
    share = share_directory("dc_interfaces")
    installed = {}
    for description in [*share.glob("msg/*.json"), *share.glob("srv/*.json")]:
        top = json.loads(description.read_text())["type_hashes"][0]
        installed[top["type_name"]] = top["hash_string"]
    # Also fails on a venv whose dc_interfaces was built before Heartbeat moved out: `make install` rebuilds it.
    assert installed == original
