"""The code reader on generated frames whose codes, contents and places are known."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import zxingcpp

from dc_measurements.camera import DETECTION_MODULES, detection
from dc_measurements.camera.detection import BarcodeDetector, Detection, draw_detections

Image = npt.NDArray[Any]  # uint8; OpenCV's stubs type every array it returns as integer-or-float
Box = tuple[int, int, int, int]  # left, top, right, bottom

# (zxing-cpp format, content written, type and data DC reports)
CODES = {
    "QRCODE": (zxingcpp.BarcodeFormat.QRCode, "LOC-A01-03", "LOC-A01-03"),
    "EAN13": (zxingcpp.BarcodeFormat.EAN13, "400638133393", "4006381333931"),
    "EAN8": (zxingcpp.BarcodeFormat.EAN8, "9638507", "96385074"),
    "UPCA": (zxingcpp.BarcodeFormat.UPCA, "03600029145", "036000291452"),
    "UPCE": (zxingcpp.BarcodeFormat.UPCE, "0123456", "01234565"),
    "CODE128": (zxingcpp.BarcodeFormat.Code128, "SKU-12345", "SKU-12345"),
    "CODE39": (zxingcpp.BarcodeFormat.Code39, "BIN42", "BIN42"),
    "DATAMATRIX": (zxingcpp.BarcodeFormat.DataMatrix, "PALLET-7", "PALLET-7"),
}


def symbol(kind: str, scale: int = 3) -> Image:
    fmt, content, _ = CODES[kind]
    image = np.asarray(zxingcpp.write_barcode_to_image(zxingcpp.create_barcode(content, fmt), scale=scale))
    return np.ascontiguousarray(image, dtype=np.uint8)


def frame(*codes: tuple[str, int, int], size: tuple[int, int] = (480, 640)) -> tuple[Image, list[Box]]:
    """A grey mono frame with each code (kind, left, top) pasted in; the box of each code's dark modules."""
    image = np.full(size, 150, np.uint8)
    boxes: list[Box] = []
    for kind, left, top in codes:
        code = symbol(kind)
        h, w = code.shape
        image[top : top + h, left : left + w] = code
        ys, xs = np.nonzero(code < 128)
        boxes.append((left + int(xs.min()), top + int(ys.min()), left + int(xs.max()) + 1, top + int(ys.max()) + 1))
    return image, boxes


def contains(detection: Detection, box: Box, slack: int = 3) -> bool:
    left, top, right, bottom = box
    if detection.type in ("EAN13", "EAN8", "UPCA", "UPCE"):
        bottom -= 5 * 3  # the guard bars reach 5 modules below the data bars, which the readers box
    return (
        detection.left <= left + slack
        and detection.top <= top + slack
        and detection.left + detection.width >= right - slack
        and detection.top + detection.height >= bottom - slack
    )


@pytest.fixture(scope="module")
def detector() -> BarcodeDetector:
    return BarcodeDetector(["barcode"])


@pytest.mark.parametrize("kind", list(CODES))
def test_each_symbology_is_read_with_its_data_type_and_place(detector: BarcodeDetector, kind: str) -> None:
    image, [box] = frame((kind, 120, 90))

    [found] = detector.detect(image)

    assert (found.type, found.data) == (kind, CODES[kind][2])
    assert contains(found, box)
    # Around the code, not the frame: no wider than the code plus its quiet zone.
    assert found.width <= box[2] - box[0] + 30 and found.height <= box[3] - box[1] + 30
    assert len(found.polygon) >= 4


def test_a_qr_code_rotated_by_90_degrees_is_read(detector: BarcodeDetector) -> None:
    image, _ = frame(("QRCODE", 200, 100))

    found = detector.detect(cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE))

    assert [(d.type, d.data) for d in found] == [("QRCODE", "LOC-A01-03")]


def test_a_slightly_blurred_qr_code_is_read(detector: BarcodeDetector) -> None:
    image, [box] = frame(("QRCODE", 200, 100))

    [found] = detector.detect(cv2.GaussianBlur(image, (0, 0), 1.2))

    assert (found.type, found.data) == ("QRCODE", "LOC-A01-03")
    assert contains(found, box)


def test_two_codes_in_one_frame_are_both_found_once_sorted_by_position(detector: BarcodeDetector) -> None:
    image, [low, high] = frame(("CODE128", 60, 300), ("QRCODE", 400, 40))

    found = detector.detect(image)

    assert [(d.type, d.data) for d in found] == [("QRCODE", "LOC-A01-03"), ("CODE128", "SKU-12345")]
    assert contains(found[0], high) and contains(found[1], low)


def test_a_code_read_by_several_passes_is_reported_once(detector: BarcodeDetector) -> None:
    # An EAN-13 is read by zxing-cpp, zbar and OpenCV alike (when they are installed).
    image, _ = frame(("EAN13", 100, 100))

    assert len(detector.detect(image)) == 1


def test_the_qr_module_reports_only_qr_codes() -> None:
    image, _ = frame(("EAN13", 40, 40), ("QRCODE", 400, 250))

    found = BarcodeDetector(["qr"]).detect(image)

    assert [(d.type, d.data) for d in found] == [("QRCODE", "LOC-A01-03")]


@pytest.mark.parametrize("value", [0, 255])
def test_a_blank_image_has_no_codes(detector: BarcodeDetector, value: int) -> None:
    assert detector.detect(np.full((480, 640, 3), value, np.uint8)) == []


def test_mono_and_bgr_images_give_the_same_codes(detector: BarcodeDetector) -> None:
    mono, _ = frame(("QRCODE", 50, 50), ("EAN8", 300, 250))

    from_mono = detector.detect(mono)

    assert len(from_mono) == 2
    assert detector.detect(cv2.cvtColor(mono, cv2.COLOR_GRAY2BGR)) == from_mono


def test_other_images_are_refused(detector: BarcodeDetector) -> None:
    with pytest.raises(ValueError, match="uint8 BGR"):
        detector.detect(np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(ValueError, match="uint8 BGR"):
        detector.detect(np.zeros((10, 10), np.float32))


def test_draw_detections_draws_around_the_code_on_a_copy(detector: BarcodeDetector) -> None:
    mono, [box] = frame(("QRCODE", 250, 150))
    image = cv2.cvtColor(mono, cv2.COLOR_GRAY2BGR)
    before = image.copy()
    found = detector.detect(image)

    drawn = draw_detections(image, found)

    assert np.array_equal(image, before)
    assert drawn.shape == image.shape
    left, top, right, bottom = box
    changed = np.any(drawn != image, axis=2)
    assert changed[top - 20 : bottom + 5, left - 5 : right + 5].any()
    assert not changed[bottom + 40 :, :].any() and not changed[:, right + 300 :].any()
    red = drawn[changed].astype(int)
    # Pure red lines; OpenCV 5 antialiases text whatever the line type, so the label's edges are blends.
    assert (red == (0, 0, 255)).all(axis=1).sum() > 0.5 * len(red)
    assert (red[:, 2] >= red[:, 1]).all() and (red[:, 0] == red[:, 1]).all()


def test_draw_detections_on_a_mono_image_gives_bgr() -> None:
    mono, _ = frame(("QRCODE", 250, 150))
    found = BarcodeDetector(["qr"]).detect(mono)

    drawn = draw_detections(mono, found)

    assert drawn.shape == (*mono.shape, 3)


def test_an_unknown_module_is_refused_with_the_known_ones() -> None:
    with pytest.raises(ValueError, match=r"unknown detection module\(s\) 'ocr'; known: qr, barcode"):
        BarcodeDetector(["qr", "ocr"])


def test_the_detector_knows_the_modules_a_configuration_may_name() -> None:
    assert tuple(detection.MODULE_TYPES) == DETECTION_MODULES


def test_the_libraries_in_use_are_reported() -> None:
    assert "zxing-cpp" in detection.available_libraries()
    assert set(detection.missing_libraries()).isdisjoint(detection.available_libraries())


def test_without_pyzbar_the_other_libraries_read_every_symbology() -> None:
    passes = detection.plan(detection.BARCODE_TYPES, ["zxing-cpp", "opencv"])

    assert {p.reader for p in passes} == {"zxing-cpp"}
    assert set().union(*(p.types for p in passes)) == detection.BARCODE_TYPES


def test_without_zxing_cpp_qr_and_1d_codes_are_still_planned() -> None:
    passes = detection.plan(detection.BARCODE_TYPES, ["pyzbar", "opencv"])

    assert set().union(*(p.types for p in passes)) == detection.BARCODE_TYPES - {"DATAMATRIX"}


def test_with_opencv_alone_qr_and_ean_upc_codes_are_still_planned() -> None:
    passes = detection.plan(detection.BARCODE_TYPES, ["opencv"])

    assert {p.reader for p in passes} == {"opencv-qr-aruco", "opencv-barcode"}
    assert set().union(*(p.types for p in passes)) == {"QRCODE", "EAN13", "EAN8", "UPCA"}


def test_a_detector_reads_with_the_libraries_it_has(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(detection, "_AVAILABLE", ("zxing-cpp", "opencv"))
    image, _ = frame(("CODE39", 60, 60), ("QRCODE", 400, 300))

    found = BarcodeDetector(["barcode"]).detect(image)

    assert [(d.type, d.data) for d in found] == [("CODE39", "BIN42"), ("QRCODE", "LOC-A01-03")]
