"""Defaults for a namespaced robot: the robot's topics DC reads (/odom, /cmd_vel, /map — the original's,
absolute) warned about under --namespace, image_services' services in the namespace, and `dc validate
--ros-args` reading the file as dc-bringup does."""

from __future__ import annotations

from pathlib import Path

from dc_bringup.validate import validate_params_file
from dc_measurements.image_services import parse_image_services, service_name
from tests.bringup_util import dc

ROBOT = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["distance_traveled", "speed", "map", "cmd_vel", "front"]
    condition_plugins: ["moving"]
    moving:
      plugin: "dc_conditions/Moving"
    distance_traveled:
      plugin: "dc_measurements/DistanceTraveled"
      odom_topic: "/odom"
    speed:
      plugin: "dc_measurements/Speed"
    map:
      plugin: "dc_measurements/Map"
      topic: "map"
    cmd_vel:
      plugin: "dc_measurements/CmdVel"
      topic: "/r1/cmd_vel"
    front:
      plugin: "dc_measurements/Camera"
      cam_name: "front"
      cam_topic: "/front/image_raw"
"""


def robot_file(tmp_path: Path, extra: str = "") -> Path:
    params = tmp_path / "robot.yaml"
    params.write_text(ROBOT + extra)
    return params


def outside(warnings: list[str]) -> list[str]:
    return [w for w in warnings if "not this robot's own topic" in w]


def test_absolute_sensor_topics_outside_the_namespace_are_warned_about_once_each_with_the_fix(tmp_path: Path) -> None:
    report = validate_params_file(robot_file(tmp_path), "r1")
    odom, camera = outside(report.warnings)
    # Three parameters name /odom, two of them by default: one warning naming all three.
    assert odom == (
        "/odom is absolute: outside namespace /r1, not this robot's own topic (measurement_server.distance_traveled"
        ".odom_topic, measurement_server.speed.odom_topic (default), measurement_server.moving.odom_topic (default)); "
        "write odom_topic: odom (relative: /r1/odom) for this robot's, or remap it (--ros-args -r /odom:=odom)"
    )
    assert camera.startswith("/front/image_raw is absolute: outside namespace /r1")
    assert "write cam_topic: front/image_raw" in camera
    # map is relative (/r1/map) and /r1/cmd_vel absolute inside the namespace: the robot's own, not warned about.
    assert not any("/map" in w or "cmd_vel" in w for w in outside(report.warnings))


def test_sensor_topics_are_not_warned_about_without_a_namespace_nor_when_remapped(tmp_path: Path) -> None:
    params = robot_file(tmp_path)
    # The original's absolute defaults keep working as they always did.
    assert outside(validate_params_file(params, "").warnings) == []
    remapped = validate_params_file(params, "r1", ["-r", "/odom:=odom", "-r", "measurement_server:/front/image_raw:=x"])
    assert outside(remapped.warnings) == []
    # A rule for another node is not this server's.
    other = validate_params_file(params, "r1", ["-r", "destination_server:/odom:=odom"])
    assert [w.split(" ")[0] for w in outside(other.warnings)] == ["/odom", "/front/image_raw"]


def test_image_services_are_in_the_namespace_by_default_and_absolute_when_written(tmp_path: Path) -> None:
    default = parse_image_services({}).node.service_namespace
    assert default == "dc/service"
    assert service_name(default, "save_image") == "dc/service/save_image"  # rcl puts it in the node's namespace
    assert service_name("/dc/service", "save_image") == "/dc/service/save_image"
    assert service_name("/", "save_image") == "/save_image"
    assert service_name("", "save_image") == "save_image"

    services = "image_services:\n  ros__parameters:\n    services: [draw_image]\n"
    relative = tmp_path / "relative.yaml"
    relative.write_text(services)
    assert validate_params_file(relative, "r1").warnings == []
    absolute = tmp_path / "absolute.yaml"
    absolute.write_text(services + "    service_namespace: /dc/service\n")
    assert validate_params_file(absolute, "").warnings == []
    assert validate_params_file(absolute, "r1").warnings == [
        "image_services.service_namespace: /dc/service is absolute: outside namespace /r1, the same services for "
        "every DC of this ROS domain; write dc/service (relative) for this DC's own"
    ]


def test_dc_validate_takes_ros_args_as_dc_bringup_does(tmp_path: Path) -> None:
    params = robot_file(tmp_path)
    plain = dc("validate", str(params))
    assert plain.returncode == 0, plain.stderr
    assert "not this robot's own topic" not in plain.stderr
    # -r __ns:= is the namespace, as for dc-bringup: the sensor topics' warnings appear.
    namespaced = dc("validate", str(params), "--ros-args", "-r", "__ns:=/r1")
    assert namespaced.returncode == 0, namespaced.stderr
    assert "warning: /odom is absolute: outside namespace /r1" in namespaced.stderr
    # -p over the file's parameters, and remaps, as the servers will read them.
    fixed = dc(
        "validate", str(params), "--namespace", "r1", "--ros-args", "-r", "/odom:=odom",
        "-p", "/r1/measurement_server:front.cam_topic:=front/image_raw",
    )  # fmt: skip
    assert fixed.returncode == 0, fixed.stderr
    assert "not this robot's own topic" not in fixed.stderr, fixed.stderr
    # A -p value the server refuses is refused here, with its path.
    refused = dc("validate", str(params), "--ros-args", "-p", "measurement_server:speed.polling_interval:=-5")
    assert refused.returncode == 2
    assert "measurement_server.speed.polling_interval" in refused.stderr
    # What rcl would refuse is refused, and the ROS arguments may end with --.
    unknown = dc("validate", str(params), "--ros-args", "--bogus")
    assert unknown.returncode == 2 and "unknown ROS argument '--bogus'" in unknown.stderr
    ended = dc("validate", "--ros-args", "-r", "__ns:=/r2", "--", str(params))
    assert ended.returncode == 0 and "outside namespace /r2" in ended.stderr, ended.stderr
