"""image_services: the original's detect_barcodes, draw_image and save_image, served by a real server process."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from dc_core.errors import ConfigError
from dc_interfaces.srv import DetectBarcode, DrawImage, SaveImage
from dc_measurements.camera.images import image_to_array
from dc_measurements.image_services import image_message, parse_image_services
from dc_sim.camera import ShelfLabel, label_frame
from tests.domains import fresh_domain_id
from tests.ros_util import wait_for

LABEL = ShelfLabel("WH1/AISLE-2/SHELF-03", "4006381330015", "EAN13")


@pytest.fixture(scope="module")
def save_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The one folder the module's server may save images in (its save_roots)."""
    return tmp_path_factory.mktemp("saved")


@pytest.fixture(scope="module")
def services(tmp_path_factory: pytest.TempPathFactory, save_root: Path) -> Iterator[tuple[Any, SingleThreadedExecutor]]:
    params = tmp_path_factory.mktemp("image_services") / "params.yaml"
    params.write_text(
        f"image_services:\n  ros__parameters:\n    detection_modules: [barcode]\n    save_roots: [{str(save_root)!r}]\n"
    )
    env = dict(os.environ, ROS_DOMAIN_ID=str(fresh_domain_id()))
    server = subprocess.Popen(
        [sys.executable, "-m", "dc_measurements.image_services", str(params), "--autostart"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        with client(int(env["ROS_DOMAIN_ID"])) as pair:
            yield pair
    finally:
        server.terminate()
        server.wait(15)


@contextlib.contextmanager
def client(domain_id: int) -> Iterator[tuple[Any, SingleThreadedExecutor]]:
    """A node of its own context in ``domain_id`` to call the services from, and its executor."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node(f"test_image_services_client_{domain_id}", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)


def call(services: tuple[Any, SingleThreadedExecutor], service_type: Any, name: str, request: Any) -> Any:
    node, executor = services
    client = node.create_client(service_type, name)

    def spin() -> None:
        executor.spin_once(timeout_sec=0.05)

    assert wait_for(client.service_is_ready, spin, 30), f"{name} never appeared"
    future = client.call_async(request)
    assert wait_for(future.done, spin, 30), f"{name} never answered"
    node.destroy_client(client)
    return future.result()


def test_detect_barcodes_reads_the_codes_of_a_frame(services: tuple[Any, SingleThreadedExecutor]) -> None:
    frame = label_frame(LABEL, 640, 480)
    response = call(
        services, DetectBarcode, "/dc/service/detect_barcodes", DetectBarcode.Request(frame=image_message(frame))
    )
    codes = {(b.type, b.data) for b in response.barcodes}
    assert codes == {("QRCODE", LABEL.qr), ("EAN13", LABEL.linear)}
    for code in response.barcodes:
        assert 0 < code.width < 640 and 0 < code.height < 480


def test_draw_image_draws_a_rectangle_and_refuses_other_shapes(services: tuple[Any, SingleThreadedExecutor]) -> None:
    blank = np.full((120, 160, 3), 255, dtype=np.uint8)
    request = DrawImage.Request(frame=image_message(blank), shape="rectangle", text="QRCODE-x")
    request.box_left, request.box_top, request.box_width, request.box_height, request.box_thickness = 40, 50, 60, 40, 3
    request.color = [0, 0, 255]
    response = call(services, DrawImage, "/dc/service/draw_image", request)
    assert response.success
    drawn = image_to_array(response.frame)
    assert drawn[50, 70].tolist() == [0, 0, 255]  # on the top edge: red in BGR
    assert drawn[70, 70].tolist() == [255, 255, 255]  # inside: untouched
    circle = DrawImage.Request(frame=image_message(blank), shape="circle")
    assert not call(services, DrawImage, "/dc/service/draw_image", circle).success


def test_save_image_writes_the_frame(services: tuple[Any, SingleThreadedExecutor], save_root: Path) -> None:
    frame = label_frame(LABEL, 640, 480)
    path = save_root / "new" / "label.png"
    response = call(
        services, SaveImage, "/dc/service/save_image", SaveImage.Request(frame=image_message(frame), path=str(path))
    )
    assert response.success
    saved = cv2.imread(str(path))
    assert saved is not None
    assert (saved == frame).all()  # PNG: lossless
    assert path.stat().st_mode & 0o777 == 0o600
    unwritable = SaveImage.Request(frame=image_message(frame), path="/proc/forbidden/label.png")
    assert not call(services, SaveImage, "/dc/service/save_image", unwritable).success


def test_save_image_writes_only_inside_its_roots(
    services: tuple[Any, SingleThreadedExecutor], save_root: Path, tmp_path: Path
) -> None:
    """Any node on the graph can call save_image: it must not choose a file outside save_roots, nor write
    through a link inside them to a file outside."""
    root = save_root
    frame = np.full((48, 64, 3), 200, dtype=np.uint8)
    outside = tmp_path / "authorized_keys"
    outside.write_text("ssh-ed25519 AAAA... operator\n")
    outside.chmod(0o600)
    before = (outside.read_bytes(), outside.stat().st_mtime_ns)

    def save(path: Path | str) -> bool:
        request = SaveImage.Request(frame=image_message(frame), path=str(path))
        return bool(call(services, SaveImage, "/dc/service/save_image", request).success)

    assert not save(outside), "a path outside save_roots"
    assert not save(root / ".." / outside.name), "a path that climbs out with .."
    (root / "escape").symlink_to(tmp_path, target_is_directory=True)
    assert not save(root / "escape" / outside.name), "a folder link inside the root that leads outside"
    (root / "link.png").symlink_to(outside)
    (root / "hard.png").hardlink_to(outside)
    assert not save(root / "link.png"), "a link inside the root to a file outside"
    assert save(root / "hard.png"), "a hard link inside the root: replaced by a new file, not written through"
    assert (outside.read_bytes(), outside.stat().st_mtime_ns) == before, "the file outside is untouched"
    assert (root / "hard.png").stat().st_nlink == 1 and cv2.imread(str(root / "hard.png")) is not None
    assert save(root / "new.png") and (root / "new.png").stat().st_mode & 0o777 == 0o600


def test_configuration_is_checked() -> None:
    assert parse_image_services({}).node.services == ["detect_barcodes", "draw_image", "save_image"]
    with pytest.raises(ConfigError, match=r"image_services\.services"):
        parse_image_services({"services": ["ocr"]})
    with pytest.raises(ConfigError, match=r"image_services\.detection_modules"):
        parse_image_services({"detection_modules": ["faces"]})
    with pytest.raises(ConfigError, match=r"image_services\.servises: unknown parameter"):
        parse_image_services({"servises": []})


@pytest.mark.e2e
def test_dc_bringup_starts_the_image_services_when_the_file_has_their_section(tmp_path: Path) -> None:
    from tests.bringup_util import Bringup

    params = tmp_path / "params.yaml"
    params.write_text(
        "image_services:\n  ros__parameters:\n    services: [detect_barcodes]\n"
        "measurement_server:\n  ros__parameters:\n    measurement_plugins: [uptime]\n"
        "    uptime:\n      plugin: dc_measurements/Uptime\n"
    )
    with Bringup(params, tmp_path / "home") as bringup:
        bringup.wait_ready()
        assert any("image_services active" in line for line in bringup.stderr)
        with client(bringup.domain_id) as services:
            frame = label_frame(LABEL, 640, 480)
            request = DetectBarcode.Request(frame=image_message(frame))
            response = call(services, DetectBarcode, "/dc/service/detect_barcodes", request)
            assert {b.data for b in response.barcodes} == {LABEL.qr, LABEL.linear}


@pytest.mark.e2e
def test_namespaced_image_services_serve_in_their_namespace_unless_written_absolute(tmp_path: Path) -> None:
    """Two robots' DCs in one domain: r1's default services are its own (/r1/dc/service/…), not the
    /dc/service/… every DC would share; r2's file writes /dc/service, honoured as written and warned about."""
    from tests.bringup_util import Bringup

    section = "image_services:\n  ros__parameters:\n    services: [draw_image]\n"
    (tmp_path / "r1.yaml").write_text(section)
    (tmp_path / "r2.yaml").write_text(section + '    service_namespace: "/dc/service"\n')
    r1 = Bringup(tmp_path / "r1.yaml", tmp_path / "r1", args=["--single-process", "--namespace", "r1"])
    r2 = Bringup(
        tmp_path / "r2.yaml",
        tmp_path / "r2",
        args=["--single-process", "--namespace", "r2"],
        env={"ROS_DOMAIN_ID": str(r1.domain_id)},
    )
    with r1, r2:
        r1.wait_ready()
        r2.wait_ready()
        with client(r1.domain_id) as services:
            request = DrawImage.Request(frame=image_message(np.zeros((48, 64, 3), dtype=np.uint8)), shape="rectangle")
            request.box_width, request.box_height = 10, 10
            assert call(services, DrawImage, "/r1/dc/service/draw_image", request).success
            assert call(services, DrawImage, "/dc/service/draw_image", request).success
            names = services[0].get_service_names_and_types()
            assert {name for name, _ in names if name.endswith("/draw_image")} == {
                "/r1/dc/service/draw_image",
                "/dc/service/draw_image",
            }
    assert not any("service_namespace" in line for line in r1.stderr), "\n".join(r1.stderr)
    (warning,) = [line for line in r2.stderr if "service_namespace" in line]
    assert "image_services.service_namespace: /dc/service is absolute: outside namespace /r2" in warning
    assert "write dc/service (relative)" in warning
