"""Map measurement: the occupancy grid of ``/map`` saved as map_saver's PGM + YAML and a PNG.

The grid arrives on a TRANSIENT_LOCAL subscription (a map server publishes it once; a late
subscriber still gets it), or a VOLATILE one with ``transient_local: false`` (a transient-local
subscription matches no volatile publisher: a QoS warning, and no map). A poll renders the newest
grid on the server's worker — the original ran ``map_saver_cli`` in a shell from its timer, holding
the server up to ``save_map_timeout`` — unless it is identical to the grid saved last: a map that
did not change is not written, nor published, again. The files are written, on the worker, once
the record is published (:meth:`Map.on_published`): a record the conditions drop leaves no file.
Width and height come from the grid (the original assumed a square map).
"""

from __future__ import annotations

import base64
import hashlib
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

from nav_msgs.msg import OccupancyGrid
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_core.errors import PluginError
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import compat_param, param
from dc_core.rostime import now_ns
from dc_core.topics import topic_param
from dc_core.worker import Outcome
from dc_measurements.map.files import map_yaml, pgm_bytes, png_bytes, trinary_image
from dc_measurements.saved_files import PendingFiles, ReservedPaths, file_locations

MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
VOLATILE_MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
_SUFFIXES = (".yaml", ".pgm", ".png")
MAP_BASE64_ESTIMATE = 1024 * 1024


@dataclass(frozen=True, kw_only=True)
class MapParams:
    topic: str = topic_param("/map", doc="nav_msgs/msg/OccupancyGrid topic")
    transient_local: bool = param(
        True,
        doc="Subscribe transient-local, as map servers publish (a map published before DC started arrives); "
        "false: volatile, for a volatile publisher (Nav2's map_subscribe_transient_local)",
    )
    save_path: str = param(
        "map/%Y-%m-%dT%H:%M:%S",
        doc="Path of the saved files without extension, under save_local_base_path/all_base_path ($ENV, strftime)",
    )
    save_map_timeout: float = param(
        3.0, minimum=0.0, doc="Seconds a poll waits for a first map when none has arrived yet"
    )
    quiet: bool = compat_param(True, "there is no map_saver output")
    save_base64: bool = param(False, doc="Also put the PNG (base64) and the YAML text in the record")
    free_thresh: float = param(0.25, minimum=0.0, maximum=1.0, doc="Occupancy at or below which a cell is free")
    occupied_thresh: float = param(0.65, minimum=0.0, maximum=1.0, doc="Occupancy at or above which a cell is occupied")


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class Map(Measurement[MapParams]):
    """The map (nav_msgs/OccupancyGrid) saved as PGM + YAML (map_saver's format) and PNG, with its metadata."""

    collect_in_worker = True

    def __init__(self, context: MeasurementContext, params: MapParams) -> None:
        super().__init__(context, params)
        self._lock = threading.Lock()
        self._grid: Any = None
        self._grid_arrived = threading.Event()
        self._saved_fingerprint: bytes | None = None
        self._subscription: Any = None
        self._pending: tuple[PendingFiles, bytes] | None = None
        self._reserved = ReservedPaths()
        self.unchanged = 0
        self.no_map = 0
        self.saved = 0
        self.save_errors = 0

    def record_bytes_estimate(self) -> int | None:
        # A trinary PNG compresses well: a 4,000 x 4,000 map (200 m at 5 cm) is well under 1 MiB in base64.
        return MAP_BASE64_ESTIMATE if self.params.save_base64 else None

    def on_configure(self) -> None:
        p = self.params
        if p.free_thresh >= p.occupied_thresh:
            raise PluginError(
                f"{self.context.name}: free_thresh ({p.free_thresh}) must be below "
                f"occupied_thresh ({p.occupied_thresh})"
            )
        self.on_cleanup()
        qos = MAP_QOS if p.transient_local else VOLATILE_MAP_QOS
        self._subscription = self.context.subscribe(OccupancyGrid, p.topic, self._on_grid, qos)

    def on_cleanup(self) -> None:
        if self._subscription is not None:
            self.context.unsubscribe(self._subscription)
            self._subscription = None
        with self._lock:
            self._grid = None
            self._grid_arrived.clear()
            self._saved_fingerprint = None

    def _on_grid(self, message: Any, info: Any = None) -> None:
        with self._lock:
            self._grid = message
        self._grid_arrived.set()

    def collect(self) -> dict[str, Any] | None:
        if not self._grid_arrived.wait(self.params.save_map_timeout):
            self.no_map += 1
            return None
        with self._lock:
            grid = self._grid
        info = grid.info
        data = bytes(grid.data)
        fingerprint = hashlib.sha256(
            repr((info.width, info.height, info.resolution, _origin(info))).encode() + data
        ).digest()
        if fingerprint == self._saved_fingerprint:
            self.unchanged += 1
            return None
        return self._prepare(info, data, fingerprint)

    def _prepare(self, info: Any, data: bytes, fingerprint: bytes) -> dict[str, Any]:
        """The record and, pending until it is published, its files."""
        p = self.params
        node_time = now_ns(self.context.node) / 1e9
        locations = self._reserved.reserve(
            file_locations(self.context.paths, p.save_path, node_time or time.time()), _SUFFIXES
        )
        image = trinary_image(info.width, info.height, data, p.free_thresh, p.occupied_thresh)
        origin = _origin(info)
        yaml_text = map_yaml(
            os.path.basename(locations.local) + ".pgm", float(info.resolution), origin, p.free_thresh, p.occupied_thresh
        )
        png = png_bytes(image)
        files = {locations.local + ".pgm": pgm_bytes(image), locations.local + ".png": png}
        files[locations.local + ".yaml"] = yaml_text.encode()
        local_paths = {path.rsplit(".", 1)[1]: path for path in files}
        record: dict[str, Any] = {
            "resolution": float(info.resolution),
            "origin": {"x": origin[0], "y": origin[1], "yaw": origin[2]},
            "width": int(info.width),
            "height": int(info.height),
            "local_paths": local_paths,
        }
        if locations.remote:
            record["remote_paths"] = {
                key: {kind: f"{path}.{kind}" for kind in ("yaml", "pgm", "png")}
                for key, path in locations.remote.items()
            }
        if p.save_base64:
            record["base64"] = {"png": base64.b64encode(png).decode("ascii"), "yaml": yaml_text}
        with self._lock:
            if self._pending is not None:
                self._reserved.release(self._pending[0].base)
            self._pending = (PendingFiles(record, locations.local, dict(files)), fingerprint)
        return record

    def on_published(self, sample: dict[str, Any]) -> None:
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is None or pending[0].sample is not sample:
            return
        files, fingerprint = pending
        # The map counts as saved from now on: the same grid is not published again while it is written.
        self._saved_fingerprint = fingerprint
        self.context.worker.submit(files.write, lambda outcome: self._written(files, outcome))

    def _written(self, files: PendingFiles, outcome: Outcome[int]) -> None:
        self._reserved.release(files.base)
        try:
            outcome.get()
            self.saved += 1
        except Exception as exc:
            self._saved_fingerprint = None  # saved again at the next poll
            self.save_errors += 1
            self.context.logger.error(f"measurement {self.context.name}: map files not saved: {exc}")

    def counters(self) -> dict[str, int]:
        return {
            "saved": self.saved,
            "unchanged": self.unchanged,
            "no_map": self.no_map,
            "save_errors": self.save_errors,
        }


def _origin(info: Any) -> tuple[float, float, float]:
    position = info.origin.position
    return float(position.x), float(position.y), _yaw(info.origin.orientation)
