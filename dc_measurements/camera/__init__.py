"""Camera measurement: frames of a robot's camera, the QR codes and barcodes in them, and their images.

The subscription only keeps the newest frame (no decoding: a 30 fps camera polled once a second
costs one conversion a second, not thirty). A poll takes that frame if no earlier poll took it,
converts it (dc_measurements.camera.images), turns it by ``rotation_angle``, reads its codes with
``detection_modules`` and builds the record with the paths its images will have. The images are
written only once the record is published (:meth:`Camera.on_published`), on the server's worker:
a frame the conditions drop leaves no file, and the server's loop never waits on JPEG encoding.

The original re-saved its last frame at every poll, wrote files for records it did not publish,
silently disabled a camera whose rotation was not a multiple of 90, and waited in configure for a
detection service.
"""

from __future__ import annotations

import base64
import functools
import threading
from dataclasses import dataclass
from typing import Any

from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_core.errors import PluginError
from dc_core.logs import BurstLog
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import compat_param, param
from dc_core.rostime import now_ns, stamp_ns
from dc_core.topics import topic_param
from dc_core.worker import Outcome
from dc_measurements.saved_files import PendingFiles, ReservedPaths, file_locations

DETECTION_MODULES = ("qr", "barcode")
# Best effort matches cameras publishing either way; depth 1: only the newest frame matters.
FRAME_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
IMAGE_KINDS = ("raw", "rotated", "inspected")
_SUFFIX = ".jpg"


def _modules_problem(modules: list[str]) -> str | None:
    unknown = [m for m in modules if m not in DETECTION_MODULES]
    return f"modules among {list(DETECTION_MODULES)} (unknown: {unknown})" if unknown else None


@dataclass(frozen=True, kw_only=True)
class CameraParams:
    cam_name: str = param(doc="Name of the camera, given as camera_name in every record")
    cam_topic: str = topic_param(
        doc="Image topic (sensor_msgs/Image, or sensor_msgs/CompressedImage: see image_type)",
    )
    image_type: str = param(
        "auto",
        choices=("auto", "raw", "compressed"),
        doc="raw: sensor_msgs/Image; compressed: sensor_msgs/CompressedImage (JPEG, PNG); auto: compressed when "
        "cam_topic ends in /compressed, as image_transport names it",
    )
    rotation_angle: int = param(
        0,
        doc="Turn the image clockwise by this many degrees before reading it (a multiple of 90; negative: "
        "counterclockwise)",
        check=lambda angle: None if angle % 90 == 0 else "a multiple of 90",
    )
    detection_modules: list[str] = param(
        [],
        doc='Readers applied to each frame: "qr" (QR codes), "barcode" (1D and 2D codes: EAN/UPC, Code 128/39, '
        "DataMatrix, QR)",
        check=_modules_problem,
    )
    draw_det_barcodes: bool = param(True, doc="Draw a box and a type-data label around each code read")
    save_raw_img: bool = param(False, doc="Save the frame as received (JPEG)")
    save_rotated_img: bool = param(False, doc="Save the turned frame (only when rotation_angle is not 0)")
    save_detections_img: bool = param(True, doc="Save the inspected frame (turned, codes drawn) when a code was read")
    save_raw_path: str = param("camera/raw/%Y-%m-%dT%H:%M:%S", doc="Path of the raw image, without .jpg")
    save_rotated_path: str = param("camera/rotated/%Y-%m-%dT%H:%M:%S", doc="Path of the turned image, without .jpg")
    save_inspected_path: str = param(
        "camera/inspected/%Y-%m-%dT%H:%M:%S", doc="Path of the inspected image, without .jpg"
    )
    save_raw_base64: bool = param(False, doc="Put the raw image (JPEG, base64) in the record")
    save_rotated_base64: bool = param(False, doc="Put the turned image (JPEG, base64) in the record")
    save_inspected_base64: bool = param(False, doc="Put the inspected image (JPEG, base64) in the record")
    jpeg_quality: int = param(90, minimum=1, maximum=100, doc="JPEG quality of saved and base64 images")
    max_decoded_pixels: int = param(
        50_000_000,
        minimum=1,
        doc="A compressed frame whose header gives more pixels is refused without being decoded "
        "(counted in frames_too_large); 50 MP decodes to 150 MB",
    )
    node_name: str = compat_param("", "the Camera subscribes through the measurement server's node")


@dataclass
class _Frame:
    message: Any
    number: int


# A 1920x1080 JPEG at quality 90 is ~0.3-0.4 MB, ~0.5 MB in base64: what one image in a record weighs.
BASE64_IMAGE_ESTIMATE = 512 * 1024


class Camera(Measurement[CameraParams]):
    """Camera frames: QR codes and barcodes read in them, and raw, turned and inspected images (JPEG)."""

    collect_in_worker = True

    def record_bytes_estimate(self) -> int | None:
        p = self.params
        images = p.save_raw_base64 + p.save_rotated_base64 + p.save_inspected_base64
        return images * BASE64_IMAGE_ESTIMATE or None

    def __init__(self, context: MeasurementContext, params: CameraParams) -> None:
        super().__init__(context, params)
        self._lock = threading.Lock()
        self._frame: _Frame | None = None
        self._frames_received = 0
        self._collected_number = 0
        self._subscription: Any = None
        self._detector: Any = None
        self._compressed = False
        self._pending: list[PendingFiles] = []
        self._reserved = ReservedPaths()
        self._bad_frame_log = BurstLog(context.logger.error, f"measurement {context.name}: frames not readable")
        self._save_log = BurstLog(context.logger.error, f"measurement {context.name}: images not saved")
        self._too_large_log = BurstLog(
            context.logger.warning, f"measurement {context.name}: frames too large to decode, refused"
        )
        self.stale = 0
        self.bad_frames = 0
        self.frames_too_large = 0
        self.saved_images = 0
        self.save_errors = 0

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        try:
            import cv2  # noqa: F401  (the conversions and JPEG encoding need it)
        except ImportError as exc:
            raise PluginError(
                f"{self.context.name}: the Camera measurement needs OpenCV ({exc}): pip install 'ros2-dc[camera]'"
            ) from None
        if p.detection_modules:
            from dc_measurements.camera.detection import BarcodeDetector

            self._detector = BarcodeDetector(p.detection_modules)
        self.on_cleanup()
        compressed = p.image_type == "compressed" or (p.image_type == "auto" and p.cam_topic.endswith("/compressed"))
        if compressed:
            from sensor_msgs.msg import CompressedImage as message_type
        else:
            from sensor_msgs.msg import Image as message_type
        self._compressed = compressed
        self._subscription = self.context.subscribe(message_type, p.cam_topic, self._on_frame, FRAME_QOS)

    def on_cleanup(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None
        with self._lock:
            self._frame = None
            pending, self._pending = self._pending, []
        for files in pending:
            self._reserved.release(files.base)

    def _on_frame(self, message: Any, info: Any = None) -> None:
        with self._lock:
            self._frames_received += 1
            self._frame = _Frame(message, self._frames_received)

    # -- collection (on the worker) ----------------------------------------------------------------
    def collect_stamped(self) -> tuple[dict[str, Any] | None, int | None, str | None]:
        with self._lock:
            frame = self._frame
            if frame is None or frame.number == self._collected_number:
                self.stale += 1
                return None, None, None
            self._collected_number = frame.number
        sample = self._inspect(frame.message)
        header_ns = stamp_ns(frame.message.header.stamp)
        # The record is dated when the picture was taken, not when it was read.
        return sample, header_ns or None, None

    def collect(self) -> dict[str, Any] | None:
        return self.collect_stamped()[0]

    def _inspect(self, message: Any) -> dict[str, Any] | None:
        from dc_measurements.camera.images import (
            FrameTooLarge,
            ImageError,
            compressed_to_array,
            encode_jpeg,
            image_to_array,
            rotate,
        )

        p = self.params
        self._bad_frame_log.tick()
        self._too_large_log.tick()
        try:
            raw = compressed_to_array(message, p.max_decoded_pixels) if self._compressed else image_to_array(message)
        except FrameTooLarge as exc:
            self.frames_too_large += 1
            self._too_large_log.event(1, str(exc))
            return None
        except ImageError as exc:
            self.bad_frames += 1
            self._bad_frame_log.event(1, str(exc))
            return None
        rotated = rotate(raw, p.rotation_angle)
        detections = self._detector.detect(rotated) if self._detector is not None else []
        images: dict[str, Any] = {}
        if p.save_raw_img or p.save_raw_base64:
            images["raw"] = raw
        if p.rotation_angle % 360 and (p.save_rotated_img or p.save_rotated_base64):
            images["rotated"] = rotated
        sample: dict[str, Any] = {"camera_name": p.cam_name}
        if detections:
            if p.save_detections_img or p.save_inspected_base64:
                if p.draw_det_barcodes:
                    from dc_measurements.camera.detection import draw_detections

                    images["inspected"] = draw_detections(rotated, detections)
                else:
                    images["inspected"] = rotated
            sample["inspected"] = {
                "barcode": [
                    {"data": d.data, "type": d.type, "top": d.top, "left": d.left, "width": d.width, "height": d.height}
                    for d in detections
                ]
            }
        saved = {"raw": p.save_raw_img, "rotated": p.save_rotated_img, "inspected": p.save_detections_img}
        in_record = {"raw": p.save_raw_base64, "rotated": p.save_rotated_base64, "inspected": p.save_inspected_base64}
        pending: list[PendingFiles] = []
        when_s = now_ns(self.context.node) / 1e9
        for kind in IMAGE_KINDS:
            if kind not in images:
                continue
            encoded = encode_jpeg(images[kind], p.jpeg_quality) if in_record[kind] else None
            if encoded is not None:
                sample.setdefault("base64", {})[kind] = base64.b64encode(encoded).decode("ascii")
            if saved[kind]:
                locations = file_locations(self.context.paths, self._save_path(kind), when_s)
                locations = self._reserved.reserve(locations, (_SUFFIX,))
                local, remote = locations.with_suffix(_SUFFIX)
                sample.setdefault("local_paths", {})[kind] = local
                for key, path in remote.items():
                    sample.setdefault("remote_paths", {}).setdefault(key, {})[kind] = path
                # JPEG encoding waits for publication too, unless the record carries the image already.
                content = (
                    encoded if encoded is not None else functools.partial(encode_jpeg, images[kind], p.jpeg_quality)
                )
                pending.append(PendingFiles(sample, locations.local, {local: content}))
        if len(sample) == 1:
            return None  # nothing read, nothing to save: no record (camera_name alone says nothing)
        with self._lock:
            for files in self._pending:  # a sample not published: its names are free again
                self._reserved.release(files.base)
            self._pending = pending
        return sample

    def _save_path(self, kind: str) -> str:
        return {
            "raw": self.params.save_raw_path,
            "rotated": self.params.save_rotated_path,
            "inspected": self.params.save_inspected_path,
        }[kind]

    # -- images of published records -----------------------------------------------------------------
    def on_published(self, sample: dict[str, Any]) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for files in pending:
            if files.sample is sample:
                self.context.worker.submit(files.write, functools.partial(self._written, files))
            else:
                self._reserved.release(files.base)

    def _written(self, files: PendingFiles, outcome: Outcome[int]) -> None:
        self._reserved.release(files.base)
        try:
            self.saved_images += outcome.get()
        except Exception as exc:
            self.save_errors += 1
            self._save_log.event(1, f"{', '.join(files.files)}: {exc}")

    def counters(self) -> dict[str, int]:
        return {
            "frames": self._frames_received,
            "stale": self.stale,
            "bad_frames": self.bad_frames,
            "frames_too_large": self.frames_too_large,
            "saved_images": self.saved_images,
            "save_errors": self.save_errors,
        }
