"""Camera: ROS images converted without cv_bridge, and the measurement fed with real frames over DDS."""

from __future__ import annotations

import base64
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image

from dc_core.errors import ConfigError
from dc_core.measurement import BasePaths
from dc_core.params import parse_params
from dc_measurements.camera import Camera
from dc_measurements.camera.images import (
    FrameTooLarge,
    ImageError,
    compressed_size,
    compressed_to_array,
    image_to_array,
    rotate,
)
from dc_sim.camera import ShelfLabel, label_frame
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, ros_session, unique

LABEL = ShelfLabel("WH1/AISLE-1/SHELF-01", "PAL-1000", "Code128")


def image_message(pixels: np.ndarray, encoding: str, *, pad: int = 0, big_endian: bool = False) -> Image:
    """A sensor_msgs/Image of ``pixels`` (rows padded with ``pad`` bytes, as some drivers do)."""
    message = Image()
    message.height, message.width = pixels.shape[:2]
    message.encoding = encoding
    message.is_bigendian = big_endian
    raw = (
        pixels.astype(">u2" if big_endian else pixels.dtype).tobytes()
        if pixels.dtype == np.uint16
        else pixels.tobytes()
    )
    row = len(raw) // message.height
    rows = [raw[i * row : (i + 1) * row] + b"\x00" * pad for i in range(message.height)]
    message.step = row + pad
    message.data = b"".join(rows)
    return message


BGR = np.array([[[10, 20, 30], [40, 50, 60]], [[70, 80, 90], [100, 110, 120]]], dtype=np.uint8)


@pytest.mark.parametrize(
    ("encoding", "pixels"),
    [
        ("bgr8", BGR),
        ("rgb8", BGR[:, :, ::-1]),
        ("bgra8", np.dstack([BGR, np.full((2, 2), 255, np.uint8)])),
        ("rgba8", np.dstack([BGR[:, :, ::-1], np.full((2, 2), 255, np.uint8)])),
    ],
)
def test_colour_encodings_become_bgr(encoding: str, pixels: np.ndarray) -> None:
    for pad in (0, 3):
        assert (image_to_array(image_message(np.ascontiguousarray(pixels), encoding, pad=pad)) == BGR).all()


def test_mono_encodings_become_8_bit_grey() -> None:
    grey = np.array([[0, 128], [200, 255]], dtype=np.uint8)
    assert (image_to_array(image_message(grey, "mono8", pad=2)) == grey).all()
    deep = np.array([[0, 32768], [51200, 65535]], dtype=np.uint16)
    for big_endian in (False, True):
        converted = image_to_array(image_message(deep, "mono16", big_endian=big_endian))
        assert converted.tolist() == [[0, 128], [200, 255]]


def test_unreadable_images_are_refused_with_the_reason() -> None:
    with pytest.raises(ImageError, match="'yuv422' is not supported"):
        image_to_array(image_message(BGR, "yuv422"))
    short = image_message(BGR, "bgr8")
    short.data = bytes(short.data)[:-1]
    with pytest.raises(ImageError, match="cannot hold its pixels"):
        image_to_array(short)
    broken = CompressedImage(format="jpeg", data=b"not a jpeg")
    with pytest.raises(ImageError, match="neither JPEG nor PNG"):
        compressed_to_array(broken, 50_000_000)
    _, jpeg = cv2.imencode(".jpg", BGR)
    damaged = CompressedImage(format="jpeg", data=jpeg.tobytes()[:-40])
    with pytest.raises(ImageError, match="could not be decoded"):
        compressed_to_array(damaged, 50_000_000)


@pytest.mark.parametrize("extension", [".jpg", ".png"])
def test_compressed_images_are_decoded(extension: str) -> None:
    frame = label_frame(LABEL, 640, 480)
    ok, encoded = cv2.imencode(extension, frame)
    assert ok
    decoded = compressed_to_array(CompressedImage(format=extension[1:], data=encoded.tobytes()), 640 * 480)
    assert decoded.shape == frame.shape
    assert np.abs(decoded.astype(int) - frame.astype(int)).mean() < 3


def jpeg_claiming(width: int, height: int) -> bytes:
    """A small real JPEG whose frame header says it is ``width`` x ``height``: what a hostile publisher sends."""
    _, encoded = cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))
    data = bytearray(encoded.tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    return bytes(data)


@pytest.mark.parametrize("params", [[], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]])
def test_the_size_of_a_compressed_frame_is_read_from_its_header(params: list[int]) -> None:
    frame = label_frame(LABEL, 640, 480)
    _, jpeg = cv2.imencode(".jpg", frame, params)
    _, png = cv2.imencode(".png", frame[:, :, 0])
    assert compressed_size(jpeg.tobytes()) == compressed_size(png.tobytes()) == (640, 480)
    assert compressed_size(jpeg_claiming(60000, 50000)) == (60000, 50000)


def test_a_frame_larger_than_max_decoded_pixels_is_refused_without_being_decoded(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 3 GP (9 GB decoded) promised by ~1 kB: OpenCV would allocate before finding the data short.
    hostile = CompressedImage(format="jpeg", data=jpeg_claiming(60000, 50000))

    def decoded(*args: Any) -> None:
        raise AssertionError("the frame was decoded")

    monkeypatch.setattr(cv2, "imdecode", decoded)
    with pytest.raises(FrameTooLarge, match=r"60000x50000 \(3000.0 MP\) is larger than max_decoded_pixels \(50 MP\)"):
        compressed_to_array(hostile, 50_000_000)
    _, png = cv2.imencode(".png", BGR)
    with pytest.raises(FrameTooLarge):
        compressed_to_array(CompressedImage(format="png", data=png.tobytes()), 3)


def test_rotation_is_clockwise_in_quarter_turns() -> None:
    image = np.array([[1, 2], [3, 4]], dtype=np.uint8)
    assert rotate(image, 90).tolist() == [[3, 1], [4, 2]]
    assert rotate(image, -90).tolist() == rotate(image, 270).tolist() == [[2, 4], [1, 3]]
    assert rotate(image, 180).tolist() == [[4, 3], [2, 1]]
    assert rotate(image, 360) is image


def test_a_rotation_that_is_not_a_quarter_turn_is_refused_at_configure() -> None:
    with pytest.raises(ConfigError, match=r"rotation_angle: expected a multiple of 90"):
        parse_params(Camera.Params, {"cam_name": "c", "cam_topic": "/c", "rotation_angle": 45}, "m.cam")
    with pytest.raises(ConfigError, match="detection_modules"):
        parse_params(Camera.Params, {"cam_name": "c", "cam_topic": "/c", "detection_modules": ["faces"]}, "m.cam")


# -- the measurement with real frames over DDS ----------------------------------------------------------


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("camera") as session:
        yield session


def started(ros: Ros, tmp_path: Path, **params: Any) -> tuple[Camera, str]:
    topic = params.pop("cam_topic", unique("/camera/image_raw"))
    plugin = ros.harness.make(Camera, {"cam_name": "front", "cam_topic": topic, **params})
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path), "robot1", {"minio": "images"})
    plugin.on_configure()
    plugin.on_activate()
    return plugin, topic


def collected(ros: Ros, plugin: Camera, publish: Any) -> dict[str, Any]:
    """Publish (again and again: best effort) until a poll gives a record."""
    record: dict[str, Any] | None = None

    def arrived() -> bool:
        nonlocal record
        record = plugin.collect()
        return record is not None

    assert ros.spin_until(arrived, publish)
    assert record is not None
    return record


def frame_message(frame: np.ndarray, stamp_s: int = 1_700_000_000) -> Image:
    message = image_message(frame, "bgr8")
    message.header.stamp.sec = stamp_s
    return message


def test_codes_are_read_and_the_inspected_image_written_only_once_published(ros: Ros, tmp_path: Path) -> None:
    plugin, topic = started(ros, tmp_path, detection_modules=["barcode"])
    publisher = ros.publisher(Image, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    frame = label_frame(LABEL, 640, 480)
    record = collected(ros, plugin, lambda: publisher.publish(frame_message(frame)))
    assert_valid(Camera, record)
    codes = {(c["type"], c["data"]) for c in record["inspected"]["barcode"]}
    assert codes == {("QRCODE", LABEL.qr), ("CODE128", LABEL.linear)}
    for code in record["inspected"]["barcode"]:
        assert 0 <= code["left"] < 640 and 0 <= code["top"] < 480 and code["width"] > 20 and code["height"] > 20
    inspected = Path(record["local_paths"]["inspected"])
    assert inspected.parent.parent == tmp_path / "robot1" / "camera"
    assert record["remote_paths"]["minio"]["inspected"].startswith("robot1/images/camera/inspected/")
    assert set(record["local_paths"]) == {"inspected"}  # save_raw_img and save_rotated_img are off
    # Nothing on disk until the record is published: a dropped record leaves no file.
    assert not inspected.exists()
    plugin.on_published(record)
    ros.harness.run_finished_work(plugin)
    saved = cv2.imread(str(inspected))
    assert saved is not None
    assert saved.shape == frame.shape
    assert stat.S_IMODE(inspected.stat().st_mode) == 0o600, "a saved image is the user's alone"
    assert (np.abs(saved.astype(int) - frame.astype(int)) > 100).any()  # the boxes were drawn
    assert plugin.counters()["saved_images"] == 1
    # The same frame is not collected (nor saved) twice.
    assert plugin.collect() is None
    assert plugin.counters()["stale"] >= 1
    ros.harness.stop(plugin)


def test_an_image_that_cannot_be_written_is_counted_and_logged_and_the_next_one_is(ros: Ros, tmp_path: Path) -> None:
    # A file where the camera's folder should be: no folder can be made there, even by root.
    blocker = tmp_path / "robot1"
    blocker.write_text("not a folder")
    plugin, topic = started(ros, tmp_path, detection_modules=["barcode"])
    publisher = ros.publisher(Image, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    frame = label_frame(LABEL, 640, 480)
    record = collected(ros, plugin, lambda: publisher.publish(frame_message(frame)))
    plugin.on_published(record)
    ros.harness.run_finished_work(plugin)
    assert (plugin.counters()["save_errors"], plugin.counters()["saved_images"]) == (1, 0)
    (error,) = ros.harness.context(plugin).logger.at("error")
    assert "images not saved" in error and record["local_paths"]["inspected"] in error
    # The camera goes on: a later frame's image is written once the folder can be made.
    blocker.unlink()
    second = collected(ros, plugin, lambda: publisher.publish(frame_message(frame, 1_700_000_001)))
    plugin.on_published(second)
    ros.harness.run_finished_work(plugin)
    assert plugin.counters()["saved_images"] == 1
    assert cv2.imread(second["local_paths"]["inspected"]) is not None
    ros.harness.stop(plugin)


def test_a_frame_without_codes_gives_no_record_and_a_dropped_record_no_file(ros: Ros, tmp_path: Path) -> None:
    plugin, topic = started(ros, tmp_path, detection_modules=["qr"], save_raw_img=True, save_raw_base64=True)
    publisher = ros.publisher(Image, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    blank = np.full((480, 640, 3), 200, dtype=np.uint8)
    record = collected(ros, plugin, lambda: publisher.publish(frame_message(blank)))
    # No code: no "inspected" (an Exist condition on it gates the record), but the raw image is asked for.
    assert "inspected" not in record and set(record["local_paths"]) == {"raw"}
    raw_jpeg = base64.b64decode(record["base64"]["raw"])
    decoded = cv2.imdecode(np.frombuffer(raw_jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None
    assert decoded.shape == (480, 640, 3)
    # This record is dropped by the server (never published): its image is never written.
    frame = label_frame(LABEL, 640, 480)
    second = collected(ros, plugin, lambda: publisher.publish(frame_message(frame, 1_700_000_001)))
    assert [c["type"] for c in second["inspected"]["barcode"]] == ["QRCODE"]  # "qr" reads QR codes only
    plugin.on_published(second)
    ros.harness.run_finished_work(plugin)
    assert Path(second["local_paths"]["raw"]).exists()
    assert not Path(record["local_paths"]["raw"]).exists()
    assert record["local_paths"]["raw"] != second["local_paths"]["raw"]
    ros.harness.stop(plugin)


def test_rotation_and_compressed_frames(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/camera") + "/compressed"
    plugin, _ = started(
        ros, tmp_path, cam_topic=topic, rotation_angle=90, detection_modules=["barcode"], save_rotated_img=True
    )
    publisher = ros.publisher(CompressedImage, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    # The camera is mounted turned: its frames show the label a quarter turn counterclockwise.
    frame = rotate(label_frame(LABEL, 640, 480), -90)
    _, png = cv2.imencode(".png", frame)
    message = CompressedImage(format="png", data=png.tobytes())
    record = collected(ros, plugin, lambda: publisher.publish(message))
    assert {c["data"] for c in record["inspected"]["barcode"]} == {LABEL.qr, LABEL.linear}
    plugin.on_published(record)
    ros.harness.run_finished_work(plugin)
    rotated = cv2.imread(record["local_paths"]["rotated"])
    assert rotated is not None
    assert rotated.shape == (480, 640, 3)  # turned back upright
    ros.harness.stop(plugin)


def test_unreadable_frames_are_counted_and_logged(ros: Ros, tmp_path: Path) -> None:
    plugin, topic = started(ros, tmp_path, detection_modules=["barcode"])
    publisher = ros.publisher(Image, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    assert ros.spin_until(
        lambda: plugin.collect() is None and plugin.counters()["bad_frames"] > 0,
        lambda: publisher.publish(image_message(BGR, "yuv422")),
    )
    assert any("'yuv422' is not supported" in line for line in ros.harness.context(plugin).logger.at("error"))
    ros.harness.stop(plugin)


def test_an_oversized_compressed_frame_is_counted_and_logged_and_the_next_frame_read(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/camera") + "/compressed"
    plugin, _ = started(ros, tmp_path, cam_topic=topic, detection_modules=["barcode"])
    publisher = ros.publisher(CompressedImage, topic, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
    hostile = CompressedImage(format="jpeg", data=jpeg_claiming(12000, 8000))  # 96 MP against the default 50
    assert ros.spin_until(
        lambda: plugin.collect() is None and plugin.counters()["frames_too_large"] > 0,
        lambda: publisher.publish(hostile),
    )
    (warning, *_) = ros.harness.context(plugin).logger.at("warning")
    assert "frames too large to decode" in warning and "12000x8000" in warning
    assert plugin.counters()["bad_frames"] == 0
    _, jpeg = cv2.imencode(".jpg", label_frame(LABEL, 640, 480))
    good = CompressedImage(format="jpeg", data=jpeg.tobytes())
    record = collected(ros, plugin, lambda: publisher.publish(good))
    assert {c["data"] for c in record["inspected"]["barcode"]} == {LABEL.qr, LABEL.linear}
    ros.harness.stop(plugin)


def test_images_in_base64_size_the_output_history() -> None:
    from dc_core.testing import PluginHarness

    def estimate(**params: Any) -> int | None:
        return PluginHarness().make(Camera, {"cam_name": "c", "cam_topic": "/c", **params}).record_bytes_estimate()

    assert estimate() is None  # files only: small records, the history keeps history_depth
    assert estimate(save_raw_base64=True) == 512 * 1024
    assert estimate(save_raw_base64=True, save_inspected_base64=True) == 1024 * 1024
