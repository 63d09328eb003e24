"""dc-bringup with a Nav2-style parameter file and ``--ros-args``, as a namespaced robot runs it.

The file keys DC's servers under the robot's namespace (``/r1: measurement_server:``) beside another
node's section and a ``/**`` section; ``--ros-args`` remaps ``/tf`` and ``/tf_static`` into the
namespace (Nav2's multi-robot bringup) and sets a parameter with ``-p``. DC's settings are then read
back through the nodes' parameter services, as ``ros2 param get`` reads them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

from tests.bringup_util import Bringup
from tests.bringup_util import dc as run_dc
from tests.robot_helpers import ros_session, tf_message, transform

pytestmark = pytest.mark.e2e

PARAMS = """\
/**:
  ros__parameters:
    use_sim_time: false
controller_server:
  ros__parameters:
    controller_frequency: 20.0
/r1:
  measurement_server:
    ros__parameters:
      measurement_plugins: ["position"]
      position:
        plugin: "dc_measurements/Position"
        tags: ["stdout"]
        topic_output: "/r1/dc/measurement/position"
        polling_interval: 200
        global_frame: "odom_e2e"
        robot_base_frame: "base_e2e"
        transform_timeout: 0.1
  destination_server:
    ros__parameters:
      flb.storage_path: "var/dc/buffer"
      destination_plugins: ["stdout"]
      stdout:
        plugin: "dc_destinations/Stdout"
        inputs: ["/r1/dc/measurement/position"]
"""
NAMESPACED_TF = ["-r", "/tf:=tf", "-r", "/tf_static:=tf_static"]


def call(executor: SingleThreadedExecutor, future: Any) -> Any:
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    assert future.done(), "no answer from the parameter service"
    return future.result()


@pytest.mark.usefixtures("bringup_mode")
def test_tf_remapped_into_the_namespace_and_parameters_served_read_only(tmp_path: Path) -> None:
    params = tmp_path / "nav2_style.yaml"
    params.write_text(PARAMS)
    ros_args = ["--ros-args", *NAMESPACED_TF, "-p", "heartbeat_period:=0.5"]
    with Bringup(params, tmp_path / "home", args=["--namespace", "r1", *ros_args]) as dc:
        # Other nodes' sections: said once, at INFO, not as warnings.
        dc.wait_stderr("sections for nodes DC does not run, ignored (other nodes' parameters): controller_server")
        dc.wait_ready()
        with ros_session("ros_args", domain_id=dc.domain_id) as ros:
            node, executor = ros.node, ros.executor
            robot_tf = node.create_publisher(TFMessage, "/r1/tf", QoSProfile(depth=10))
            other_tf = node.create_publisher(TFMessage, "/tf", QoSProfile(depth=10))
            deadline = time.monotonic() + 30.0

            def robot_seen() -> bool:
                # Each publish is stamped now; the other robot's pose is on /tf, this one's on /r1/tf.
                now_ns = node.get_clock().now().nanoseconds
                robot_tf.publish(tf_message(transform("odom_e2e", "base_e2e", 1.0, 0.0, 0.0, stamp_ns=now_ns)))
                other_tf.publish(tf_message(transform("odom_e2e", "base_e2e", 5.0, 0.0, 0.0, stamp_ns=now_ns)))
                executor.spin_once(timeout_sec=0.05)
                return len(dc.named("position")) >= 3 or time.monotonic() > deadline

            while not robot_seen():
                pass
            positions = dc.named("position")
            assert len(positions) >= 3, "\n".join(dc.stderr[-40:])
            assert all(record["x"] == pytest.approx(1.0) for record in positions), positions

            client = AsyncParameterClient(node, "/r1/measurement_server")
            assert client.wait_for_services(timeout_sec=10.0)
            names = call(executor, client.list_parameters()).result.names
            assert {"measurement_plugins", "position.global_frame", "heartbeat_period", "use_sim_time"} <= set(names)
            values = call(executor, client.get_parameters(["position.global_frame", "heartbeat_period"])).values
            assert values[0].type == ParameterType.PARAMETER_STRING and values[0].string_value == "odom_e2e"
            assert values[1].type == ParameterType.PARAMETER_DOUBLE and values[1].double_value == 0.5  # from -p
            described = call(executor, client.describe_parameters(["position.polling_interval"])).descriptors
            assert described[0].read_only
            refused = call(executor, client.set_parameters([Parameter("position.polling_interval", value=100)]))
            assert not refused.results[0].successful and "read-only" in refused.results[0].reason

            destinations = AsyncParameterClient(node, "/r1/destination_server")
            assert destinations.wait_for_services(timeout_sec=10.0)
            got = call(executor, destinations.get_parameters(["heartbeat_period", "stdout.inputs"])).values
            assert got[0].double_value == 0.5
            assert list(got[1].string_array_value) == ["/r1/dc/measurement/position"]


def test_a_remap_to_a_topic_of_another_type_is_an_error_naming_both(tmp_path: Path) -> None:
    params = tmp_path / "nav2_style.yaml"
    params.write_text(PARAMS)
    # DC checks the type of the publishers its graph knows when it subscribes. Started at once, its
    # servers configured before discovery had told them of this test's publisher (seen at load 3):
    # they are started only once this node sees them, by when they have seen this node too.
    bringup = Bringup(
        params, tmp_path / "home", args=["--namespace", "r1", "--no-autostart", "--ros-args", "-r", "/tf:=chatter"]
    )
    with ros_session("ros_args", domain_id=bringup.domain_id) as ros:
        node = ros.node
        chatter = node.create_publisher(String, "/r1/chatter", QoSProfile(depth=1))
        with bringup as dc:
            dc.wait_stderr("DC is waiting for startup", 120)
            deadline = time.monotonic() + 60
            while ("measurement_server", "/r1") not in node.get_node_names_and_namespaces():
                assert time.monotonic() < deadline, "measurement_server not discovered in 60 s"
                ros.executor.spin_once(timeout_sec=0.1)
            run_dc("lifecycle", "startup", "--namespace", "r1", env=dc.env)
            dc.wait_stderr("/tf: remapped to /r1/chatter, which carries std_msgs/msg/String", 60)
            line = dc.wait_stderr("tf2_msgs/msg/TFMessage expected")
            assert "activate failed" in line or "configure failed" in line, line
        chatter.destroy()


@pytest.mark.usefixtures("bringup_mode")
def test_ros_arguments_rcl_would_refuse_stop_dc_bringup_before_any_server_starts(tmp_path: Path) -> None:
    params = tmp_path / "nav2_style.yaml"
    params.write_text(PARAMS)
    for ros_args, message in (
        (["--frobnicate"], "invalid configuration: --ros-args: unknown ROS argument '--frobnicate'"),
        (["-p", "a:=[1, x]"], "invalid --ros-args: "),  # rcl's own refusal: a list of mixed types
    ):
        with Bringup(params, tmp_path / "home", args=["--ros-args", *ros_args, "-r", "__ns:=/r1"]) as dc:
            assert dc.wait_exit(30) == 2
            dc.wait_stderr(message)
            assert not [line for line in dc.stderr if "measurement_server" in line and "active" in line]
