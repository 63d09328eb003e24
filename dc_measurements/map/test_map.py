"""Map: the files map_saver would write, from a real OccupancyGrid published over DDS."""

from __future__ import annotations

import base64
import stat
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from nav_msgs.msg import OccupancyGrid
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_core.measurement import BasePaths
from dc_measurements.map import Map
from dc_measurements.map.files import FREE, OCCUPIED, UNKNOWN, trinary_image
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, ros_session, unique

MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def expected_pixel(cell: int, free: int = 25, occupied: int = 65) -> int:
    """map_saver's trinary rule, cell by cell."""
    if cell < 0 or cell > 100:
        return UNKNOWN
    if cell <= free:
        return FREE
    if cell >= occupied:
        return OCCUPIED
    return UNKNOWN


def test_trinary_thresholds_and_row_order() -> None:
    # 5 wide, 2 high: the bottom row (first in the grid) is the image's last row.
    bottom = [-1, 0, 25, 26, 64]
    top = [65, 100, 101, 127, 50]
    image = trinary_image(5, 2, np.array(bottom + top, dtype=np.int8).tobytes(), 0.25, 0.65)
    assert image.tolist() == [[expected_pixel(c) for c in top], [expected_pixel(c) for c in bottom]]
    assert image.tolist()[1] == [UNKNOWN, FREE, FREE, UNKNOWN, UNKNOWN]


def test_a_grid_whose_size_does_not_match_is_refused() -> None:
    with pytest.raises(ValueError, match="holds 3 cells"):
        trinary_image(2, 2, b"\x00\x00\x00", 0.25, 0.65)


def read_pgm(path: Path) -> np.ndarray:
    content = path.read_bytes()
    magic, size, maxval, pixels = content.split(b"\n", 3)
    assert (magic, maxval) == (b"P5", b"255")
    width, height = map(int, size.split())
    return np.frombuffer(pixels, dtype=np.uint8).reshape(height, width)


def read_png(content: bytes) -> np.ndarray:
    """A minimal reader of what a greyscale PNG must hold: the chunks with valid CRCs, the rows unfiltered."""
    assert content[:8] == b"\x89PNG\r\n\x1a\n"
    offset, chunks = 8, dict[bytes, bytes]()
    while offset < len(content):
        (length,) = struct.unpack(">I", content[offset : offset + 4])
        kind, body = content[offset + 4 : offset + 8], content[offset + 8 : offset + 8 + length]
        (crc,) = struct.unpack(">I", content[offset + 8 + length : offset + 12 + length])
        assert crc == zlib.crc32(kind + body), kind
        chunks[kind] = chunks.get(kind, b"") + body
        offset += 12 + length
    width, height, depth, colour = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (depth, colour) == (8, 0)
    rows = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), dtype=np.uint8).reshape(height, width + 1)
    assert not rows[:, 0].any()  # filter "none" on every row
    return rows[:, 1:]


def grid(width: int, height: int, seed: int) -> OccupancyGrid:
    message = OccupancyGrid()
    message.header.frame_id = "map"
    message.info.width, message.info.height, message.info.resolution = width, height, 0.05
    message.info.origin.position.x, message.info.origin.position.y = -1.5, -2.0
    rng = np.random.default_rng(seed)
    message.data = rng.choice([-1, 0, 10, 30, 50, 70, 90, 100], size=width * height).astype(np.int8).tolist()
    return message


def collected(ros: Ros, plugin: Map) -> dict[str, Any]:
    """The first record a poll gives while the node spins (the grid has to arrive first)."""
    record: dict[str, Any] | None = None

    def saved() -> bool:
        nonlocal record
        record = plugin.collect()
        return record is not None

    assert ros.spin_until(saved)
    assert record is not None
    return record


def publish_record(ros: Ros, plugin: Map, record: dict[str, Any]) -> None:
    """What the server does once it published the record: the plugin writes its files on the worker."""
    plugin.on_published(record)
    ros.harness.run_finished_work(plugin)


@pytest.fixture
def ros() -> Iterator[Ros]:
    with ros_session("map") as session:
        yield session


def test_map_saves_pgm_yaml_and_png_of_a_non_square_grid_once(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/map")
    # The map server published before DC started: TRANSIENT_LOCAL delivers it anyway.
    publisher = ros.node.create_publisher(OccupancyGrid, topic, MAP_QOS)
    published = grid(37, 23, seed=1)
    publisher.publish(published)
    plugin = ros.harness.make(
        Map, {"topic": topic, "save_path": "maps/%Y/map", "save_base64": True, "save_map_timeout": 0.0}
    )
    # strftime tokens in every part of the path (the default save_local_base_path ends in %Y/%m/%d/%H).
    ros.harness.context(plugin).paths = BasePaths(f"{tmp_path}/%Y", "robot1", {"minio": "bucket-prefix"})
    plugin.on_configure()
    plugin.on_activate()
    record = collected(ros, plugin)
    assert_valid(Map, record)
    # The files are written once the record is published: a record the server drops leaves none.
    assert not list(tmp_path.rglob("map.*"))
    publish_record(ros, plugin, record)
    assert (record["width"], record["height"]) == (37, 23)
    assert record["resolution"] == pytest.approx(0.05)
    assert record["origin"] == {"x": -1.5, "y": -2.0, "yaw": 0.0}
    year = Path(record["local_paths"]["pgm"]).parent.name
    assert record["local_paths"]["pgm"] == str(tmp_path / year / "robot1" / "maps" / year / "map.pgm")
    assert record["remote_paths"] == {
        "minio": {kind: f"robot1/bucket-prefix/maps/{year}/map.{kind}" for kind in ("yaml", "pgm", "png")}
    }

    # Pixel for pixel what map_saver's rule gives for the published grid, top row first.
    cells = np.array(published.data, dtype=np.int16).reshape(23, 37)
    expected = np.vectorize(expected_pixel)(cells)[::-1]
    assert (read_pgm(Path(record["local_paths"]["pgm"])) == expected).all()
    png = Path(record["local_paths"]["png"]).read_bytes()
    assert (read_png(png) == expected).all()
    assert base64.b64decode(record["base64"]["png"]) == png

    metadata = yaml.safe_load(Path(record["local_paths"]["yaml"]).read_text())
    assert metadata == {
        "image": "map.pgm",
        "mode": "trinary",
        "resolution": pytest.approx(0.05),
        "origin": [-1.5, -2.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.25,
    }
    assert record["base64"]["yaml"] == Path(record["local_paths"]["yaml"]).read_text()
    # The map's files are the user's alone, whatever the umask of the process.
    assert {stat.S_IMODE(Path(path).stat().st_mode) for path in record["local_paths"].values()} == {0o600}

    # The same map again: not written, not published.
    assert plugin.collect() is None
    assert (plugin.counters()["saved"], plugin.counters()["unchanged"]) == (1, 1)

    # A changed map in the same second: new files beside the first ones, which stay as they were.
    publisher.publish(grid(37, 23, seed=2))
    changed = collected(ros, plugin)
    publish_record(ros, plugin, changed)
    assert changed["local_paths"] != record["local_paths"]
    assert (read_pgm(Path(record["local_paths"]["pgm"])) == expected).all()
    assert not list(tmp_path.rglob("*.part"))
    ros.harness.stop(plugin)


def test_a_map_that_cannot_be_saved_is_counted_logged_and_saved_at_the_next_poll(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/map")
    publisher = ros.node.create_publisher(OccupancyGrid, topic, MAP_QOS)
    publisher.publish(grid(8, 5, seed=3))
    # A file where the map's folder should be: no folder can be made there, even by root.
    blocker = tmp_path / "robot1"
    blocker.write_text("not a folder")
    plugin = ros.harness.make(Map, {"topic": topic, "save_path": "maps/map", "save_map_timeout": 0.0})
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path), "robot1")
    plugin.on_configure()
    plugin.on_activate()
    first = collected(ros, plugin)
    publish_record(ros, plugin, first)
    assert plugin.counters()["save_errors"] == 1 and plugin.counters()["saved"] == 0
    (error,) = ros.harness.context(plugin).logger.at("error")
    assert "map files not saved" in error
    assert not Path(first["local_paths"]["pgm"]).exists()

    # The same map is not taken as saved: once the folder can be made, the next poll saves it.
    blocker.unlink()
    again = collected(ros, plugin)
    publish_record(ros, plugin, again)
    assert plugin.counters()["saved"] == 1
    assert (read_pgm(Path(again["local_paths"]["pgm"])).shape) == (5, 8)
    ros.harness.stop(plugin)


def test_a_volatile_map_publisher_is_read_with_transient_local_false(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/map")
    volatile = ros.harness.make(Map, {"topic": topic, "transient_local": False, "save_map_timeout": 0.0})
    default = ros.harness.make(Map, {"topic": topic, "save_map_timeout": 0.0})
    for plugin in (volatile, default):
        ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
        plugin.on_configure()
        plugin.on_activate()
    volatile_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
    # Matched by the volatile subscription only: a transient-local one does not match a volatile
    # publisher (the QoS warning, and no map, of the default).
    publisher = ros.publisher(OccupancyGrid, topic, volatile_qos)
    assert publisher.get_subscription_count() == 1
    publisher.publish(grid(6, 4, seed=5))
    record = collected(ros, volatile)
    assert (record["width"], record["height"]) == (6, 4)
    assert default.collect() is None and default.counters()["no_map"] == 1
    for plugin in (volatile, default):
        ros.harness.stop(plugin)


def test_no_map_reports_nothing_after_save_map_timeout(ros: Ros, tmp_path: Path) -> None:
    plugin = ros.harness.make(Map, {"topic": unique("/map"), "save_map_timeout": 0.2})
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    assert plugin.collect() is None
    assert plugin.counters()["no_map"] == 1
    assert not list(tmp_path.iterdir())
    ros.harness.stop(plugin)


def test_thresholds_in_the_wrong_order_are_refused() -> None:
    from dc_core.errors import PluginError
    from dc_core.testing import PluginHarness

    with pytest.raises(PluginError, match="free_thresh"):
        PluginHarness().start(Map, {"free_thresh": 0.7, "occupied_thresh": 0.6})


def test_a_map_in_base64_sizes_the_output_history_for_records_of_a_mebibyte() -> None:
    from dc_core.record_history import DEFAULT_HISTORY_BYTES, history_depth_for
    from dc_core.testing import PluginHarness

    harness = PluginHarness()
    assert harness.make(Map, {}).record_bytes_estimate() is None  # paths and sizes only: small
    estimate = harness.make(Map, {"save_base64": True}).record_bytes_estimate()
    assert history_depth_for(estimate or 0, 1000, DEFAULT_HISTORY_BYTES) == 64
