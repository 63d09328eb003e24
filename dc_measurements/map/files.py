"""An occupancy grid as map_saver writes it (PGM + YAML, trinary), plus a PNG of the same pixels.

Written by DC itself: the original ran ``map_saver_cli`` in a shell from its timer. The thresholds
and pixel values are map_saver's (nav2_map_server, trinary mode): an unknown cell (-1, or outside
0..100) is 205, a cell at most ``free_thresh`` is free (254), at least ``occupied_thresh`` occupied (0),
anything between unknown (205). The image's first row is the grid's last (images grow downwards,
maps upwards).
"""

from __future__ import annotations

import struct
import zlib
from typing import Any

import numpy as np
import numpy.typing as npt

FREE = 254
OCCUPIED = 0
UNKNOWN = 205


def trinary_image(
    width: int, height: int, data: Any, free_thresh: float, occupied_thresh: float
) -> npt.NDArray[np.uint8]:
    """The grid's cells (row-major from the bottom row, as nav_msgs/OccupancyGrid) as image rows, top first."""
    cells = np.frombuffer(bytes(data), dtype=np.int8)
    if cells.size != width * height:
        raise ValueError(f"the grid holds {cells.size} cells, not width*height = {width}*{height}")
    cells = cells.reshape(height, width).astype(np.int16)
    # map_saver rounds the thresholds to whole percents (std::rint: half to even, as round()).
    free_limit, occupied_limit = round(free_thresh * 100.0), round(occupied_thresh * 100.0)
    known = (cells >= 0) & (cells <= 100)
    image = np.full((height, width), UNKNOWN, dtype=np.uint8)
    image[known & (cells <= free_limit)] = FREE
    image[known & (cells >= occupied_limit)] = OCCUPIED
    return np.ascontiguousarray(image[::-1])


def pgm_bytes(image: npt.NDArray[np.uint8]) -> bytes:
    height, width = image.shape
    return f"P5\n{width} {height}\n255\n".encode() + image.tobytes()


def png_bytes(image: npt.NDArray[np.uint8]) -> bytes:
    """An 8-bit greyscale PNG (no imaging library needed: a PNG is a few zlib-compressed chunks)."""
    height, width = image.shape
    rows = np.hstack([np.zeros((height, 1), dtype=np.uint8), image])  # filter type 0 before each row

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def map_yaml(
    image_file: str, resolution: float, origin: tuple[float, float, float], free_thresh: float, occupied_thresh: float
) -> str:
    """map_server's metadata file; ``image`` is relative to the YAML file, as map_saver writes it."""
    x, y, yaw = origin
    return (
        f"image: {image_file}\n"
        "mode: trinary\n"
        f"resolution: {resolution!r}\n"
        f"origin: [{x!r}, {y!r}, {yaw!r}]\n"
        "negate: 0\n"
        f"occupied_thresh: {occupied_thresh!r}\n"
        f"free_thresh: {free_thresh!r}\n"
    )
