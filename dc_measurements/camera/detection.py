"""Reading QR codes and barcodes in camera frames: which library reads what, chosen by measurement.

The detector runs a fixed plan of passes and keeps each code once (same type and data, overlapping
boxes). The plan comes from benchmarks/barcode_detection.py (640x480 generated shelf frames, 12 per
cell, 2 cores, 2026-11-24; docs/camera.md has the full table). Codes read with the right data and
place, over all 13 variations (module size 1-4 px, rotation 15/45/90, tilt, blur, noise, low light,
three codes per frame), and the mean time per frame:

    type        zxing-cpp   pyzbar   cv2.barcode   cv2 QR (Aruco)   DC detector
    QRCODE      77% 3.9ms   60% 12ms     -           20% 7.2ms       85% 21ms
    EAN13       65%         76%      75% 2.7ms          -            85%
    EAN8        64%         82%      76%                -            84%
    UPCA        68%         75%      76%                -            85%
    UPCE        60%         88%       0%                -            91%
    CODE128     76%         77%       0%                -            79%
    CODE39      57%         83%       0% (*)            -            84%
    DATAMATRIX  67%          -         -                -            85%

- zxing-cpp, on the frame as it is, for every type: the fastest (4 ms), the only one reading
  DataMatrix and 1-px-module codes, and the one that reads tilted EAN/UPC codes.
- zxing-cpp again on the frame upscaled 2x, for QR and DataMatrix: small (1.5 px modules), tilted and
  blurred matrix codes (QR 77 -> 85%, DataMatrix 67 -> 85%) for ~9 ms more.
- pyzbar for the 1D types: it reads what zxing-cpp misses under blur (sigma 1) and low light
  (EAN-13 0 -> 100%, Code 39 17 -> 92%) and UPC-E at 45 degrees.
- cv2.barcode is not used although it alone reads EAN/UPC at 45 degrees: (*) it made 69 EAN/UPC reads with
  made-up digits out of 156 Code 39 frames, and wrong data is worse than a miss. It and
  cv2.QRCodeDetectorAruco are the last resort when neither zxing-cpp nor pyzbar can be imported.
  cv2.QRCodeDetector (classic) read 5% of the QR codes.
- Grayscale first (all libraries binarise a mono image; one conversion for all passes). CLAHE
  equalisation before zxing-cpp changed its rates by -11 to +8 points for 2.5x the time: not used.

Without pyzbar (libzbar0 not installed), the 2x zxing-cpp pass covers every type, its best second
chance for low-light 1D codes; without zxing-cpp, pyzbar reads QR and 1D codes and DataMatrix is lost.
available_libraries() and missing_libraries() say which is the case, for the measurement to log once.

Nothing reads codes at a Gaussian blur of sigma 2 at 2.5 px modules, nor 1D codes at 45 degrees
except EAN-8/UPC-E; 1-px QR and DataMatrix codes are mostly missed.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType, ModuleType
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

Image = npt.NDArray[Any]  # uint8; OpenCV's stubs type every array it returns as integer-or-float

QR_TYPES = frozenset({"QRCODE"})
BARCODE_TYPES = frozenset({"QRCODE", "EAN13", "EAN8", "UPCA", "UPCE", "CODE128", "CODE39", "DATAMATRIX"})
# Keyed by the names configurations use (the camera's DETECTION_MODULES, declared there without importing
# OpenCV; this module is imported by the camera, not the other way round).
MODULE_TYPES: Mapping[str, frozenset[str]] = MappingProxyType({"qr": QR_TYPES, "barcode": BARCODE_TYPES})

ZXING = "zxing-cpp"
ZBAR = "pyzbar"
OPENCV = "opencv"


def _optional(name: str) -> tuple[ModuleType | None, str | None]:
    """The module, or None and why: pyzbar raises ImportError when libzbar0 is not installed."""
    try:
        return importlib.import_module(name), None
    except (ImportError, OSError) as error:
        return None, f"{type(error).__name__}: {error}"


# Imported by name rather than statically: either may be missing on a robot, and the detector then
# works with what is left instead of failing at import.
_zxingcpp, _ZXING_ERROR = _optional("zxingcpp")
_pyzbar, _ZBAR_ERROR = _optional("pyzbar.pyzbar")
_MISSING: Mapping[str, str] = MappingProxyType(
    {name: error for name, error in ((ZXING, _ZXING_ERROR), (ZBAR, _ZBAR_ERROR)) if error is not None}
)
_AVAILABLE = tuple(name for name in (ZXING, ZBAR, OPENCV) if name not in _MISSING)


def available_libraries() -> tuple[str, ...]:
    """The decoding libraries importable here, in the detector's order of preference."""
    return _AVAILABLE


def missing_libraries() -> Mapping[str, str]:
    """Libraries the detector would use but cannot import, with the import error (log it once)."""
    return _MISSING


@dataclass(frozen=True)
class Detection:
    """One decoded code: its text, its type in DC's (zbar's) names, and where it is in the image."""

    data: str
    type: str
    left: int
    top: int
    width: int
    height: int
    polygon: tuple[tuple[int, int], ...]

    def overlaps(self, other: Detection) -> bool:
        """Boxes touch or overlap (inclusive, so that a zero-width box of a thin 1D read still counts)."""
        return (
            self.left <= other.left + other.width
            and other.left <= self.left + self.width
            and self.top <= other.top + other.height
            and other.top <= self.top + self.height
        )


def _detection(data: str, kind: str, points: Sequence[tuple[float, float]], shape: tuple[int, ...]) -> Detection:
    height, width = shape[:2]
    polygon = tuple((round(x), round(y)) for x, y in points)
    xs = [x for x, _ in polygon]
    ys = [y for _, y in polygon]
    left, top = min(max(min(xs), 0), width), min(max(min(ys), 0), height)
    right, bottom = min(max(max(xs), 0), width), min(max(max(ys), 0), height)
    return Detection(data, kind, left, top, right - left, bottom - top, polygon)


def _normalised(kind: str, data: str) -> tuple[str, str]:
    """DC's convention for the EAN/UPC family, which is zbar's with UPC-A enabled.

    A UPC-A is an EAN-13 whose first digit is 0 (the same bars): it is reported as UPCA with its 12
    digits, whichever way the library named it. zxing-cpp reports UPC-A and UPC-E expanded to 13 digits.
    """
    if kind in ("EAN13", "UPCA") and len(data) == 13 and data.startswith("0"):
        return "UPCA", data[1:]
    return kind, data


# --- zxing-cpp -----------------------------------------------------------------------------------

_ZXING_NAMES: Mapping[str, str] = MappingProxyType(
    {
        "QRCode": "QRCODE",
        "EAN13": "EAN13",
        "EAN8": "EAN8",
        "UPCA": "UPCA",
        "UPCE": "UPCE",
        "Code128": "CODE128",
        "Code39": "CODE39",
        "DataMatrix": "DATAMATRIX",
    }
)


def read_zxing(gray: Image, types: frozenset[str]) -> list[Detection]:
    """zxing-cpp, restricted to the wanted formats (fewer formats: faster, and no stray symbologies)."""
    if _zxingcpp is None:
        return []
    zx: Any = _zxingcpp
    formats = [getattr(zx.BarcodeFormat, name) for name, kind in _ZXING_NAMES.items() if kind in types]
    if not formats:
        return []
    found: list[Detection] = []
    for code in zx.read_barcodes(gray, formats=zx.BarcodeFormats(formats)):
        kind = _ZXING_NAMES.get(code.format.name)
        if kind is None:
            continue
        data: str = code.text
        if kind == "UPCE" and isinstance(code.extra, dict) and isinstance(code.extra.get("UPCE"), str):
            data = code.extra["UPCE"]  # the 8 digits printed under the bars, as zbar reports them
        kind, data = _normalised(kind, data)
        if kind not in types:
            continue
        position = code.position
        corners = (position.top_left, position.top_right, position.bottom_right, position.bottom_left)
        found.append(_detection(data, kind, [(p.x, p.y) for p in corners], gray.shape))
    return found


# --- pyzbar (zbar) ------------------------------------------------------------------------------

_ZBAR_TYPES = ("QRCODE", "EAN13", "EAN8", "UPCA", "UPCE", "CODE128", "CODE39")  # zbar reads no DataMatrix


def read_zbar(gray: Image, types: frozenset[str]) -> list[Detection]:
    """pyzbar; UPC-A and UPC-E are enabled explicitly, else zbar reports both as EAN-13."""
    if _pyzbar is None:
        return []
    zbar: Any = _pyzbar
    wanted = [getattr(zbar.ZBarSymbol, kind) for kind in _ZBAR_TYPES if kind in types]
    if not wanted:
        return []
    found: list[Detection] = []
    pixels = np.ascontiguousarray(gray)
    for code in zbar.decode((pixels.tobytes(), pixels.shape[1], pixels.shape[0]), symbols=wanted):
        kind, data = _normalised(str(code.type), bytes(code.data).decode("utf-8", errors="replace"))
        if kind in types:
            found.append(_detection(data, kind, [(p.x, p.y) for p in code.polygon], gray.shape))
    return found


# --- OpenCV -------------------------------------------------------------------------------------


def _opencv_points(points: Any, count: int) -> list[list[tuple[float, float]]]:
    if points is None:
        return [[] for _ in range(count)]
    array = np.asarray(points, dtype=np.float64).reshape(-1, 4, 2)
    return [[(float(x), float(y)) for x, y in quad] for quad in array]


def _read_opencv_qr(detector: Any, gray: Image, types: frozenset[str]) -> list[Detection]:
    if "QRCODE" not in types:
        return []
    ok, texts, points, _ = detector.detectAndDecodeMulti(gray)
    if not ok:
        return []
    quads = _opencv_points(points, len(texts))
    return [_detection(text, "QRCODE", quad, gray.shape) for text, quad in zip(texts, quads, strict=False) if text]


def read_opencv_qr(gray: Image, types: frozenset[str]) -> list[Detection]:
    """OpenCV's classic QRCodeDetector."""
    return _read_opencv_qr(cv2.QRCodeDetector(), gray, types)


def read_opencv_qr_aruco(gray: Image, types: frozenset[str]) -> list[Detection]:
    """OpenCV's QRCodeDetectorAruco (finder patterns found as ArUco-like markers)."""
    return _read_opencv_qr(cv2.QRCodeDetectorAruco(), gray, types)


def read_opencv_barcode(gray: Image, types: frozenset[str]) -> list[Detection]:
    """OpenCV's cv2.barcode (EAN/UPC family; other 1D types only where its version decodes them)."""
    if not types - {"QRCODE", "DATAMATRIX"}:
        return []
    ok, texts, kinds, points = cv2.barcode.BarcodeDetector().detectAndDecodeWithType(gray)
    if not ok:
        return []
    found: list[Detection] = []
    for text, name, quad in zip(texts, kinds, _opencv_points(points, len(texts)), strict=False):
        kind, data = _normalised(str(name).replace("_", "").upper(), str(text))
        if data and kind in types:
            found.append(_detection(data, kind, quad, gray.shape))
    return found


Reader = Callable[[Image, frozenset[str]], list[Detection]]

# Every reader the benchmark compares, by the name its table uses.
READERS: Mapping[str, Reader] = MappingProxyType(
    {
        "zxing-cpp": read_zxing,
        "pyzbar": read_zbar,
        "opencv-qr": read_opencv_qr,
        "opencv-qr-aruco": read_opencv_qr_aruco,
        "opencv-barcode": read_opencv_barcode,
    }
)


# --- the detector -------------------------------------------------------------------------------


def to_gray(image: Image) -> Image:
    """The mono image every library reads; ValueError for anything but uint8 BGR or mono."""
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"expected a uint8 BGR (h, w, 3) or mono (h, w) image, got {image.dtype} {image.shape}")
    if image.ndim == 2:
        return image
    gray: Image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return gray


def upscaled(gray: Image, factor: int) -> Image:
    big: Image = cv2.resize(gray, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)
    return big


def _scaled(detection: Detection, factor: int, shape: tuple[int, ...]) -> Detection:
    points = [(x / factor, y / factor) for x, y in detection.polygon]
    return _detection(detection.data, detection.type, points, shape)


def deduplicated(detections: Sequence[Detection]) -> list[Detection]:
    """Each code once: a later read of the same type and data whose box overlaps an earlier one is dropped."""
    kept: list[Detection] = []
    for detection in detections:
        if not any(
            seen.type == detection.type and seen.data == detection.data and seen.overlaps(detection) for seen in kept
        ):
            kept.append(detection)
    return kept


MATRIX_TYPES = frozenset({"QRCODE", "DATAMATRIX"})
LINEAR_TYPES = BARCODE_TYPES - MATRIX_TYPES
# cv2.barcode decoded no UPC-E, Code 128 or Code 39 in the benchmark: only asked for what it reads.
_OPENCV_BARCODE_TYPES = frozenset({"EAN13", "EAN8", "UPCA"})


@dataclass(frozen=True)
class Pass:
    """One read of the frame: a library, the types asked of it, and the upscaling factor of the frame."""

    reader: str
    types: frozenset[str]
    upscale: int = 1


def plan(types: frozenset[str], libraries: Sequence[str]) -> tuple[Pass, ...]:
    """The passes that read the given types with the given libraries, best first (see the module docstring)."""
    passes: list[Pass] = []
    matrix, linear = types & MATRIX_TYPES, types & LINEAR_TYPES
    zxing, zbar = ZXING in libraries, ZBAR in libraries
    if zxing:
        passes.append(Pass("zxing-cpp", types))
        # Upscaled, zxing-cpp reads small, tilted and blurred matrix codes it missed, and without zbar
        # it is the best second chance for low-light 1D codes too.
        passes.append(Pass("zxing-cpp", matrix if zbar else types, upscale=2))
    if zbar:
        # zbar reads the blurred and low-light 1D codes zxing-cpp misses; without zxing-cpp, QR codes too.
        passes.append(Pass("pyzbar", linear if zxing else types - {"DATAMATRIX"}))
    if not zxing and not zbar and OPENCV in libraries:
        # A last resort only: cv2.barcode reads other 1D codes as EAN/UPC with made-up digits.
        passes.append(Pass("opencv-qr-aruco", types & {"QRCODE"}))
        passes.append(Pass("opencv-barcode", types & _OPENCV_BARCODE_TYPES))
    return tuple(p for p in passes if p.types)


class BarcodeDetector:
    """Reads the codes of the given detection modules in BGR or mono frames (see the module docstring)."""

    def __init__(self, modules: Sequence[str]) -> None:
        unknown = [module for module in modules if module not in MODULE_TYPES]
        if unknown:
            raise ValueError(
                f"unknown detection module(s) {', '.join(map(repr, unknown))}; known: {', '.join(MODULE_TYPES)}"
            )
        types: frozenset[str] = frozenset()
        for module in modules:
            types |= MODULE_TYPES[module]
        self.modules = tuple(modules)
        self.types = types
        self.passes = plan(types, available_libraries())

    def detect(self, image: Image) -> list[Detection]:
        """Every code of the detector's types in the image, once each, sorted by (top, left)."""
        gray = to_gray(image)
        found: list[Detection] = []
        larger: dict[int, Image] = {}
        for step in self.passes:
            read = READERS[step.reader]
            if step.upscale == 1:
                found += read(gray, step.types)
                continue
            if step.upscale not in larger:
                larger[step.upscale] = upscaled(gray, step.upscale)
            found += [_scaled(d, step.upscale, gray.shape) for d in read(larger[step.upscale], step.types)]
        return sorted(deduplicated(found), key=lambda d: (d.top, d.left))


# --- drawing ------------------------------------------------------------------------------------


def draw_detections(image: Image, detections: Sequence[Detection]) -> Image:
    """A BGR copy with a red polygon around each code and the label f"{type}-{data}" above it, as the original drew."""
    canvas: Image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    height, width = canvas.shape[:2]
    thickness = max(2, min(height, width) // 200)
    scale = max(0.5, min(height, width) / 960)
    red = (0, 0, 255)
    for detection in detections:
        if len(detection.polygon) >= 3:
            points = np.array(detection.polygon, dtype=np.int32).reshape(-1, 1, 2)
            cv2.polylines(canvas, [points], True, red, thickness, cv2.LINE_8)
        else:
            corner = (detection.left + detection.width, detection.top + detection.height)
            cv2.rectangle(canvas, (detection.left, detection.top), corner, red, thickness, cv2.LINE_8)
        label = f"{detection.type}-{detection.data}"
        (_, text_height), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
        # Above the box as the original drew it, but inside the frame for a code at the top edge.
        y = (
            detection.top - 10
            if detection.top - 10 >= text_height
            else detection.top + detection.height + text_height + 5
        )
        cv2.putText(canvas, label, (detection.left, y), cv2.FONT_HERSHEY_SIMPLEX, scale, red, thickness, cv2.LINE_8)
    return canvas
