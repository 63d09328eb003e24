"""Which library reads which code: detection rate and time per frame on generated shelf labels.

Each frame is a 640x480 grey shelf with a white label holding one code (three in "multi"), drawn
with zxing-cpp's writer and warped into place, then degraded. Symbologies: the ones DC's Camera
measurement promises (QR, EAN-13/8, UPC-A/E, Code 128, Code 39, DataMatrix). Variations: module
size from 1 to 4 px (the code's size in the frame), in-plane rotation 15/45/90°, a tilted shelf
(perspective), Gaussian blur, noise, low light (darkened + noise), three codes per frame.

A read counts when a library returns the code's data under DC's type name (see
dc_measurements/camera/detection.py) with its box's centre inside the code's drawn box; the rate
is over codes, the time is the mean wall time per frame, one library at a time on one core
(OpenCV's own threads are limited to 1 so that libraries compare fairly). Seeded: the frames are the
same on every run.

    .venv/bin/python benchmarks/barcode_detection.py            # ~3 min on 2 cores
    .venv/bin/python benchmarks/barcode_detection.py --quick    # a look, < 20 s
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import zxingcpp

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dc_measurements.camera import detection  # noqa: E402  (the repository root is not on the path of a script)

Image = npt.NDArray[Any]  # uint8; OpenCV's stubs type every array it returns as integer-or-float
FRAME_W, FRAME_H = 640, 480
BASE_MODULE_PX = 2.5

SYMBOLOGIES = ("QRCODE", "EAN13", "EAN8", "UPCA", "UPCE", "CODE128", "CODE39", "DATAMATRIX")
_FORMATS = {
    "QRCODE": zxingcpp.BarcodeFormat.QRCode,
    "EAN13": zxingcpp.BarcodeFormat.EAN13,
    "EAN8": zxingcpp.BarcodeFormat.EAN8,
    "UPCA": zxingcpp.BarcodeFormat.UPCA,
    "UPCE": zxingcpp.BarcodeFormat.UPCE,
    "CODE128": zxingcpp.BarcodeFormat.Code128,
    "CODE39": zxingcpp.BarcodeFormat.Code39,
    "DATAMATRIX": zxingcpp.BarcodeFormat.DataMatrix,
}


@dataclass(frozen=True)
class Variation:
    name: str
    module_px: float = BASE_MODULE_PX
    rotation_deg: float = 0.0
    tilt: float = 0.0  # 0..1: how much the far edge of the label shrinks (a shelf seen at an angle)
    blur_sigma: float = 0.0
    noise_sigma: float = 0.0
    light: float = 1.0  # multiplies the frame's brightness
    codes: int = 1


VARIATIONS = (
    Variation("1px", module_px=1.0),
    Variation("1.5px", module_px=1.5),
    Variation("2.5px (base)"),
    Variation("4px", module_px=4.0),
    Variation("rot15", rotation_deg=15),
    Variation("rot45", rotation_deg=45),
    Variation("rot90", rotation_deg=90),
    Variation("tilted", tilt=0.35),
    Variation("blur1", blur_sigma=1.0),
    Variation("blur2", blur_sigma=2.0),
    Variation("noise", noise_sigma=18),
    Variation("lowlight", light=0.15, noise_sigma=4),
    Variation("multi3", module_px=2.0, codes=3),
)
QUICK_VARIATIONS = ("1px", "2.5px (base)", "rot45", "tilted", "blur2", "lowlight", "multi3")


@dataclass(frozen=True)
class Code:
    kind: str
    data: str  # as DC reports it
    box: tuple[int, int, int, int]  # left, top, right, bottom of the drawn symbol in the frame


@dataclass(frozen=True)
class Frame:
    image: Image  # BGR
    codes: tuple[Code, ...]


def random_content(kind: str, rng: random.Random) -> str:
    digits = "0123456789"
    if kind == "QRCODE":
        return f"LOC-A{rng.randint(1, 40):02d}-{rng.randint(1, 9)}-{rng.randint(0, 99999):05d}"
    if kind == "EAN13":
        return str(rng.randint(1, 9)) + "".join(rng.choice(digits) for _ in range(11))  # not 0: that is a UPC-A
    if kind == "EAN8":
        return "".join(rng.choice(digits) for _ in range(7))
    if kind == "UPCA":
        return "".join(rng.choice(digits) for _ in range(11))
    if kind == "UPCE":
        # Number system 0, last digit 5-9 (its 5th digit then must not be 0): always a valid zero suppression.
        return "0" + "".join(rng.choice(digits) for _ in range(4)) + rng.choice("123456789") + rng.choice("56789")
    if kind == "CODE128":
        return f"SKU-{rng.randint(0, 999999):06d}"
    if kind == "CODE39":
        return "".join(rng.choice("ABCDEFGHJKLMNPRSTUVWXYZ0123456789") for _ in range(6))
    return f"PALLET-{rng.randint(0, 9999):04d}-{rng.choice('ABCDEF')}"


def symbol(kind: str, content: str) -> tuple[Image, str]:
    """The code at 1 px per module with its quiet zones, and the data DC should report for it."""
    barcode = zxingcpp.create_barcode(content, _FORMATS[kind])
    image = np.ascontiguousarray(np.asarray(zxingcpp.write_barcode_to_image(barcode, scale=1)), dtype=np.uint8)
    text = barcode.text
    if kind == "UPCA":
        text = text[1:]  # zxing-cpp writes the 13-digit GTIN; DC reports UPC-A's 12 digits
    elif kind == "UPCE":
        text = content + text[-1]  # UPC-E's check digit is that of its UPC-A expansion
    return image, text


def shelf(rng: np.random.Generator) -> Image:
    """A mid-grey shelf with a smooth shading and a few darker horizontal edges."""
    y = np.linspace(0, 1, FRAME_H, dtype=np.float32)[:, None]
    x = np.linspace(0, 1, FRAME_W, dtype=np.float32)[None, :]
    base = 120 + 40 * x - 30 * y + rng.normal(0, 3, (FRAME_H, FRAME_W)).astype(np.float32)
    for edge in rng.integers(0, FRAME_H, 3):
        base[edge : edge + 6, :] -= 50
    shaded: Image = np.clip(base, 0, 255).astype(np.uint8)
    return shaded


def place(
    frame: Image, code: Image, centre: tuple[float, float], variation: Variation, rng: np.random.Generator
) -> tuple[int, int, int, int]:
    """Warp the code (on a white label) into the frame; its bounding box in the frame."""
    module = variation.module_px
    # Downscaled with area averaging first: warping a 1-px-module image by a fraction aliases the bars.
    label = cv2.resize(
        code, (round(code.shape[1] * module), round(code.shape[0] * module)), interpolation=cv2.INTER_AREA
    )
    pad = max(4, round(2 * module))
    label = cv2.copyMakeBorder(label, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=245)
    h, w = label.shape
    source = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)
    target = source - np.array([w / 2, h / 2], dtype=np.float32)
    if variation.tilt:
        # The right edge farther away: shorter and, seen at an angle, the label narrower.
        shrink = variation.tilt
        target = target * np.array([1 - shrink / 2, 1], dtype=np.float32)
        target[1:3, 1] *= 1 - shrink
    angle = math.radians(variation.rotation_deg + rng.uniform(-1.5, 1.5))
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]], dtype=np.float32)
    target = target @ rotation.T + np.array(centre, dtype=np.float32)
    homography = cv2.getPerspectiveTransform(source, target.astype(np.float32))
    warped = cv2.warpPerspective(label, homography, (FRAME_W, FRAME_H), flags=cv2.INTER_LINEAR, borderValue=0)
    mask = cv2.warpPerspective(np.full_like(label, 255), homography, (FRAME_W, FRAME_H), flags=cv2.INTER_LINEAR)
    alpha = mask.astype(np.float32) / 255
    frame[:] = (alpha * warped + (1 - alpha) * frame).astype(np.uint8)
    inner = np.array([[pad, pad], [w - pad, pad], [w - pad, h - pad], [pad, h - pad]], dtype=np.float32)
    corners = cv2.perspectiveTransform(inner.reshape(-1, 1, 2), homography).reshape(-1, 2)
    return (
        int(corners[:, 0].min()),
        int(corners[:, 1].min()),
        math.ceil(corners[:, 0].max()),
        math.ceil(corners[:, 1].max()),
    )


def make_frame(kind: str, variation: Variation, seed: int) -> Frame:
    rng = np.random.default_rng(seed)
    pyrng = random.Random(seed)
    gray = shelf(rng)
    codes: list[Code] = []
    for index in range(variation.codes):
        symbol_image, data = symbol(kind, random_content(kind, pyrng))
        if variation.codes == 1:
            size = max(symbol_image.shape) * variation.module_px * 1.5
            margin_x = min(FRAME_W / 2 - 1, size / 2 + 10)
            margin_y = min(FRAME_H / 2 - 1, size / 2 + 10)
            centre = (
                float(rng.uniform(margin_x, FRAME_W - margin_x)),
                float(rng.uniform(margin_y, FRAME_H - margin_y)),
            )
        else:
            # One code per horizontal band, so that they never overlap.
            band = FRAME_H / variation.codes
            centre = (float(rng.uniform(FRAME_W * 0.4, FRAME_W * 0.6)), band * (index + 0.5))
        box = place(gray, symbol_image, centre, variation, rng)
        codes.append(Code(kind, data, box))
    image: Image = gray.astype(np.float32)
    if variation.blur_sigma:
        image = cv2.GaussianBlur(image, (0, 0), variation.blur_sigma)
    image *= variation.light
    if variation.noise_sigma:
        image += rng.normal(0, variation.noise_sigma, image.shape).astype(np.float32)
    mono = np.clip(image, 0, 255).astype(np.uint8)
    return Frame(cv2.cvtColor(mono, cv2.COLOR_GRAY2BGR), tuple(codes))


def correct(code: Code, found: list[detection.Detection]) -> bool:
    left, top, right, bottom = code.box
    slack = 4
    for d in found:
        cx, cy = d.left + d.width / 2, d.top + d.height / 2
        if (
            d.type == code.kind
            and d.data == code.data
            and left - slack <= cx <= right + slack
            and top - slack <= cy <= bottom + slack
        ):
            return True
    return False


Candidate = Callable[[Image], list[detection.Detection]]


def candidates() -> dict[str, tuple[Candidate, frozenset[str]]]:
    """What to compare: each library alone (on the frame's grey image), its second passes, and DC's detector."""
    all_types = detection.BARCODE_TYPES
    linear = all_types - {"QRCODE", "DATAMATRIX"}

    def reader(name: str, types: frozenset[str]) -> Candidate:
        read = detection.READERS[name]
        return lambda image: read(detection.to_gray(image), types)

    def upscaled(name: str, types: frozenset[str]) -> Candidate:
        read = detection.READERS[name]

        def run(image: Image) -> list[detection.Detection]:
            gray = detection.to_gray(image)
            return [detection._scaled(d, 2, gray.shape) for d in read(detection.upscaled(gray, 2), types)]

        return run

    def equalised(name: str, types: frozenset[str]) -> Candidate:
        read = detection.READERS[name]
        clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
        return lambda image: read(clahe.apply(detection.to_gray(image)), types)

    combined = detection.BarcodeDetector(["barcode"])
    table: dict[str, tuple[Candidate, frozenset[str]]] = {}
    if detection.ZXING in detection.available_libraries():
        table["zxing-cpp"] = (reader("zxing-cpp", all_types), all_types)
        table["zxing-cpp 2x"] = (upscaled("zxing-cpp", all_types), all_types)
        table["zxing-cpp CLAHE"] = (equalised("zxing-cpp", all_types), all_types)
    if detection.ZBAR in detection.available_libraries():
        zbar_types = all_types - {"DATAMATRIX"}
        table["pyzbar"] = (reader("pyzbar", zbar_types), zbar_types)
        table["pyzbar 2x"] = (upscaled("pyzbar", zbar_types), zbar_types)
    table["opencv-qr"] = (reader("opencv-qr", frozenset({"QRCODE"})), frozenset({"QRCODE"}))
    table["opencv-qr-aruco"] = (reader("opencv-qr-aruco", frozenset({"QRCODE"})), frozenset({"QRCODE"}))
    table["opencv-barcode"] = (reader("opencv-barcode", linear), linear)
    table["DC detector"] = (combined.detect, all_types)
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer frames and variations (< 20 s)")
    parser.add_argument("--frames", type=int, default=None, help="frames per symbology x variation (12; quick: 2)")
    parser.add_argument("--seed", type=int, default=20260101)
    parser.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "barcode_detection.json"))
    args = parser.parse_args()
    cv2.setNumThreads(1)
    frames_per_cell = args.frames or (2 if args.quick else 12)
    variations = [v for v in VARIATIONS if not args.quick or v.name in QUICK_VARIATIONS]
    table = candidates()
    missing = detection.missing_libraries()
    if missing:
        print("not available:", "; ".join(f"{name} ({error})" for name, error in missing.items()))

    results: dict[str, dict[str, dict[str, dict[str, float]]]] = {name: {} for name in table}
    started = time.perf_counter()
    for kind_index, kind in enumerate(SYMBOLOGIES):
        for variation_index, variation in enumerate(variations):
            frames = [
                make_frame(kind, variation, args.seed + 1000 * kind_index + 50 * variation_index + i)
                for i in range(frames_per_cell)
            ]
            for name, (run, types) in table.items():
                if kind not in types:
                    continue
                found_codes = total_codes = wrong = 0
                elapsed = 0.0
                for frame in frames:
                    t0 = time.perf_counter()
                    found = run(frame.image)
                    elapsed += time.perf_counter() - t0
                    hits = [code for code in frame.codes if correct(code, found)]
                    found_codes += len(hits)
                    total_codes += len(frame.codes)
                    wrong += len(found) - len(hits)
                results[name].setdefault(kind, {})[variation.name] = {
                    "rate": found_codes / total_codes,
                    "ms": elapsed / len(frames) * 1000,
                    "wrong": wrong,
                }
        print(f"{kind} done ({time.perf_counter() - started:.0f} s)", file=sys.stderr, flush=True)

    print_tables(results, [v.name for v in variations], frames_per_cell)
    payload = {
        "date": datetime.date.today().isoformat(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "versions": {"opencv": cv2.__version__, "zxing-cpp": metadata.version("zxing-cpp")},
        "libraries_available": list(detection.available_libraries()),
        "frames_per_cell": frames_per_cell,
        "frame": [FRAME_W, FRAME_H],
        "seed": args.seed,
        "quick": args.quick,
        "results": results,
        "seconds": time.perf_counter() - started,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(payload, indent=2) + "\n")
    print(f"\n{time.perf_counter() - started:.0f} s; JSON: {args.json}")


def print_tables(
    results: dict[str, dict[str, dict[str, dict[str, float]]]], variations: list[str], frames: int
) -> None:
    """Per symbology: rate (%) per library x variation, and each library's mean ms per frame."""
    print(f"\nDetection rate (% of codes read with the right data and place), {frames} frame(s) per cell, 640x480")
    for kind in SYMBOLOGIES:
        names = [name for name in results if kind in results[name]]
        print(f"\n### {kind}\n")
        print("| library | " + " | ".join(variations) + " | all | ms/frame |")
        print("|---|" + "---:|" * (len(variations) + 2))
        for name in names:
            cells = results[name][kind]
            rates = [cells[v]["rate"] for v in variations]
            ms = sum(cells[v]["ms"] for v in variations) / len(variations)
            row = " | ".join(f"{100 * r:.0f}" for r in rates)
            print(f"| {name} | {row} | {100 * sum(rates) / len(rates):.0f} | {ms:.1f} |")


if __name__ == "__main__":
    main()
