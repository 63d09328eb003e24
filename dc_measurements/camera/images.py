"""ROS images as OpenCV arrays, without cv_bridge (the PyPI ``cv-bridge`` is ROS 1's and breaks with numpy 2).

``sensor_msgs/Image`` in the encodings cameras publish (rgb8, bgr8, rgba8, bgra8, mono8, mono16, and
their aliases 8UC1/8UC3/8UC4/16UC1) and ``sensor_msgs/CompressedImage`` (JPEG, PNG) become BGR or
single-channel 8-bit arrays: what the detectors read and JPEG files hold. Rows padded beyond
``width * channels`` (``step``) and big-endian 16-bit data are handled.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

Image = npt.NDArray[np.uint8]

# encoding -> (channels, bytes per channel, conversion to BGR/mono from the channel order)
_ENCODINGS: dict[str, tuple[int, int, str]] = {
    "bgr8": (3, 1, ""),
    "8UC3": (3, 1, ""),
    "rgb8": (3, 1, "rgb"),
    "bgra8": (4, 1, "bgra"),
    "8UC4": (4, 1, "bgra"),
    "rgba8": (4, 1, "rgba"),
    "mono8": (1, 1, ""),
    "8UC1": (1, 1, ""),
    "mono16": (1, 2, "16"),
    "16UC1": (1, 2, "16"),
}
SUPPORTED_ENCODINGS = tuple(_ENCODINGS)


class ImageError(ValueError):
    """An image message that cannot be converted (its encoding, or data that does not match its size)."""


class FrameTooLarge(ImageError):
    """A compressed frame whose header promises more pixels than the camera may decode."""


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (SOF0-SOF15 but DHT, JPG and DAC, which share the range): they carry the size.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field (TEM, RST0-7), skipped when walking the segments.
_JPEG_STANDALONE = frozenset([0x01, *range(0xD0, 0xD8)])


def compressed_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's or PNG's header, read without decoding anything.

    OpenCV allocates what the header says before it decodes a pixel: a few hundred bytes of
    JPEG can ask for gigabytes. Other formats OpenCV would decode (TIFF, WebP, BMP…) are refused
    here, as they are not what ``sensor_msgs/CompressedImage`` carries."""
    if data.startswith(_PNG_SIGNATURE):
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ImageError("PNG without its IHDR header")
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if not data.startswith(b"\xff\xd8"):
        raise ImageError("compressed image is neither JPEG nor PNG")
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            raise ImageError("JPEG with a damaged header")
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in _JPEG_STANDALONE:
            at += 2
            continue
        length = int.from_bytes(data[at + 2 : at + 4], "big")
        if marker in _JPEG_SOF:
            if at + 9 > len(data):
                break
            height = int.from_bytes(data[at + 5 : at + 7], "big")
            width = int.from_bytes(data[at + 7 : at + 9], "big")
            return width, height
        if marker == 0xDA or length < 2:  # image data before any size: not a frame we can judge
            break
        at += 2 + length
    raise ImageError("JPEG without a frame header giving its size")


def image_to_array(message: Any) -> Image:
    """A ``sensor_msgs/Image`` as a BGR (h, w, 3) or mono (h, w) uint8 array (a copy: the message may go)."""
    encoding = str(message.encoding)
    if encoding not in _ENCODINGS:
        raise ImageError(f"image encoding {encoding!r} is not supported (supported: {', '.join(SUPPORTED_ENCODINGS)})")
    channels, depth, conversion = _ENCODINGS[encoding]
    height, width, step = int(message.height), int(message.width), int(message.step)
    row = width * channels * depth
    data = np.frombuffer(bytes(message.data), dtype=np.uint8)
    if step < row or data.size < step * height or height == 0 or width == 0:
        raise ImageError(
            f"{encoding} image of {width}x{height} with step {step} cannot hold its pixels in {data.size} bytes"
        )
    rows = data[: step * height].reshape(height, step)[:, :row]
    if depth == 2:
        dtype = ">u2" if message.is_bigendian else "<u2"
        # 16-bit depth or IR images are saved and read as 8 bits: keep the most significant byte.
        pixels16 = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
        return (pixels16 >> 8).astype(np.uint8)
    pixels = rows.reshape(height, width, channels) if channels > 1 else rows.reshape(height, width)
    if conversion == "rgb":
        return np.ascontiguousarray(pixels[:, :, ::-1])
    if conversion == "bgra":
        return np.ascontiguousarray(pixels[:, :, :3])
    if conversion == "rgba":
        return np.ascontiguousarray(pixels[:, :, 2::-1])
    return np.array(pixels, copy=True)


def compressed_to_array(message: Any, max_pixels: int) -> Image:
    """A ``sensor_msgs/CompressedImage`` (JPEG or PNG) as a BGR or mono uint8 array.

    Raises :class:`FrameTooLarge` without decoding when its header gives more than ``max_pixels``."""
    import cv2

    data = bytes(message.data)
    width, height = compressed_size(data)
    if width * height > max_pixels:
        raise FrameTooLarge(
            f"compressed image of {width}x{height} ({width * height / 1e6:.1f} MP) is larger than "
            f"max_decoded_pixels ({max_pixels / 1e6:g} MP): not decoded"
        )
    decoded = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise ImageError(f"compressed image ({message.format or 'no format'}) could not be decoded")
    if decoded.dtype != np.uint8:
        decoded = (decoded.astype(np.uint16) >> 8).astype(np.uint8)
    if decoded.ndim == 3 and decoded.shape[2] == 4:
        decoded = decoded[:, :, :3]
    return np.ascontiguousarray(decoded)


def rotate(image: Image, angle: int) -> Image:
    """``image`` turned clockwise by ``angle`` degrees, a multiple of 90 (negative: counterclockwise)."""
    quarter_turns = (angle // 90) % 4
    # np.rot90 turns counterclockwise for positive k.
    return np.ascontiguousarray(np.rot90(image, k=-quarter_turns)) if quarter_turns else image


def encode_jpeg(image: Image, quality: int) -> bytes:
    import cv2

    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ImageError("JPEG encoding failed")
    return bytes(encoded.tobytes())
