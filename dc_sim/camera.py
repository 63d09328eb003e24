"""What the simulated robot's camera sees: the shelf label of the waypoint it is at, or a bare shelf.

Each waypoint of the warehouse route faces a shelf whose label carries a QR code and a 1D code
(Code 128 or EAN-13, alternately), so DC's Camera measurement has something to read where the robot
stops. A label is in view whenever the robot is within :data:`LABEL_RANGE_M` of its waypoint — also
while it drives up to it or away — so that only the measurement's own gating (``if_none_conditions:
[moving]``) keeps it from saving frames taken on the move. Frames are rendered once and reused: the
simulator must stay cheap next to what it tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dc_sim.kinematics import Pose2D, Waypoint

Frame = npt.NDArray[np.uint8]

# How close (m) to a waypoint its label is in the camera's view.
LABEL_RANGE_M = 0.6
_SHELF_GREY = 200


@dataclass(frozen=True)
class ShelfLabel:
    """The codes on the shelf at one waypoint: a QR code and a 1D code (zxing-cpp's format names)."""

    qr: str
    linear: str
    linear_format: str  # "Code128" or "EAN13"


def shelf_labels(route: list[Waypoint]) -> list[ShelfLabel]:
    """One label per waypoint of ``route``; EAN-13 values carry their check digit."""
    labels = []
    for i, _ in enumerate(route):
        if i % 2 == 0:
            labels.append(ShelfLabel(f"WH1/AISLE-{i // 2 + 1}/SHELF-{i + 1:02d}", f"PAL-{1000 + i}", "Code128"))
        else:
            labels.append(ShelfLabel(f"WH1/AISLE-{i // 2 + 1}/SHELF-{i + 1:02d}", ean13(f"400638133{i:03d}"), "EAN13"))
    return labels


def ean13(first12: str) -> str:
    """``first12`` with its EAN-13 check digit."""
    total = sum(int(d) * (3 if k % 2 else 1) for k, d in enumerate(first12))
    return first12 + str((10 - total % 10) % 10)


def _code_image(text: str, format_name: str, scale: int) -> Frame:
    import zxingcpp

    barcode = zxingcpp.create_barcode(text, getattr(zxingcpp.BarcodeFormat, format_name))
    return np.array(zxingcpp.write_barcode_to_image(barcode, scale=scale), dtype=np.uint8)


def _shelf(width: int, height: int) -> Frame:
    """A grey shelf front with two darker boards: something for a detector to look at, and not read."""
    frame = np.full((height, width, 3), _SHELF_GREY, dtype=np.uint8)
    for top in (height // 6, height - height // 5):
        frame[top : top + height // 20] = 90
    return frame


def _paste(frame: Frame, image: Frame, top: int, left: int) -> None:
    h, w = image.shape[:2]
    frame[top : top + h, left : left + w] = image[:, :, None] if image.ndim == 2 else image


def label_frame(label: ShelfLabel, width: int, height: int) -> Frame:
    """The shelf with its white label, the QR code on the left and the 1D code on the right."""
    frame = _shelf(width, height)
    qr = _code_image(label.qr, "QRCode", max(2, height // 110))
    linear = _code_image(label.linear, label.linear_format, max(2, width // 300))
    margin = width // 20
    label_height = max(qr.shape[0], linear.shape[0]) + 2 * margin
    label_width = qr.shape[1] + linear.shape[1] + 3 * margin
    top, left = (height - label_height) // 2, (width - label_width) // 2
    if top < 0 or left < 0:
        raise ValueError(f"a {width}x{height} frame is too small for the shelf labels")
    frame[top : top + label_height, left : left + label_width] = 255
    _paste(frame, qr, top + margin, left + margin)
    _paste(frame, linear, top + margin + (qr.shape[0] - linear.shape[0]) // 2, left + 2 * margin + qr.shape[1])
    return frame


class CameraView:
    """The frames of one camera: rendered on first use, then the same array for every frame of a view."""

    def __init__(self, route: list[Waypoint], width: int, height: int) -> None:
        self.route = route
        self.labels = shelf_labels(route)
        self.width, self.height = width, height
        self._frames: dict[int | None, Frame] = {}

    def label_in_view(self, pose: Pose2D) -> int | None:
        """The index of the waypoint whose label the camera sees at ``pose`` (map frame), if any."""
        for i, waypoint in enumerate(self.route):
            if math.hypot(pose.x - waypoint.x, pose.y - waypoint.y) <= LABEL_RANGE_M:
                return i
        return None

    def frame(self, label: int | None) -> Frame:
        if label not in self._frames:
            self._frames[label] = (
                _shelf(self.width, self.height)
                if label is None
                else label_frame(self.labels[label], self.width, self.height)
            )
        return self._frames[label]
