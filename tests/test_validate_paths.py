"""`dc validate` warns when the files of several robots can land at the same object key."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from dc_bringup.validate import validate_params_file

REPO = Path(__file__).resolve().parent.parent


def params(tmp_path: Path, **node: object) -> Path:
    section = {
        "measurement_plugins": ["shots"],
        "shots": {"plugin": "dc_measurements/Dummy", "remote_keys": ["minio"], "remote_prefixes": [""]},
        **node,
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"measurement_server": {"ros__parameters": section}}))
    return path


def collisions(path: Path) -> list[str]:
    return [w for w in validate_params_file(path).warnings if "holds no robot name" in w]


@pytest.mark.parametrize(
    ("node", "warned"),
    [
        ({}, True),  # the defaults: $HOME/ros2/data/%Y/… and no all_base_path
        ({"all_base_path": "%Y/%m/%d"}, True),
        (
            {
                "all_base_path": "=robot_name/%Y",
                "custom_str_params_list": ["robot_name"],
                "custom_str_params": {"robot_name": {"name": "robot_name", "value": "C3PO"}},
            },
            False,
        ),
        ({"all_base_path": "$ROBOT_ID/%Y"}, False),
        ({"all_base_path": "c3po/%Y"}, False),  # a literal folder: taken for the robot's name
    ],
)
def test_object_keys_without_a_robot_name_are_warned_about(
    tmp_path: Path, node: dict[str, object], warned: bool
) -> None:
    found = collisions(params(tmp_path, **node))
    assert bool(found) == warned, found
    if warned:
        assert found[0].startswith("measurement_server.all_base_path: ")
        assert "shots" in found[0] and "=robot_name/%Y/%m/%d/%H" in found[0]


def test_the_storage_demos_name_the_robot(tmp_path: Path) -> None:
    for demo in ("tb3_pgsql_minio", "qr_codes"):
        document = yaml.safe_load((REPO / "params" / "demos" / f"{demo}.yaml").read_text())
        path = tmp_path / f"{demo}.yaml"  # the measurement server's section: the others read the environment
        path.write_text(yaml.safe_dump({"measurement_server": document["measurement_server"]}))
        assert collisions(path) == [], demo
