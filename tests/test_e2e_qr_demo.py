"""The seed's QR-code demo (params/demos/qr_codes.yaml) on `dc sim`'s camera, as the README runs it.

The simulator's truth file says where the robot stood and which shelf label was in view; the demo's
records and images must agree: every label of the route read, nothing saved while moving, no frame
saved twice.
"""

from __future__ import annotations

import bisect
import json
import subprocess
from pathlib import Path
from typing import Any

import cv2
import pytest
import yaml

from dc_sim.camera import shelf_labels
from dc_sim.warehouse import warehouse_route
from tests.bringup_util import BIN, REPO, Bringup

pytestmark = pytest.mark.e2e

# Simulated time at the wall clock's pace: at twice it, on a loaded machine the camera's frames lagged
# the simulated clock by 2 s and a stop could pass without a frame taken while standing.
RATE = 1.0
DURATION_S = 76.0  # the route's six stops take about a minute, and the last needs its second poll


def test_every_shelf_code_of_the_route_is_read_once_per_stop_and_only_while_standing(tmp_path: Path) -> None:
    truth_file = tmp_path / "truth.jsonl"
    with Bringup(REPO / "params" / "demos" / "qr_codes.yaml", tmp_path, args=["--use-sim-time"]) as dc:
        dc.wait_ready()
        sim = subprocess.run(
            [
                *(str(BIN / "dc"), "sim", "--clock", "--rate", str(RATE), "--duration", str(DURATION_S)),
                *("--truth", str(truth_file), "--wait-subscribers", "20"),
            ],
            env=dc.env,
            capture_output=True,
            text=True,
            timeout=DURATION_S / RATE + 60,
        )
        assert sim.returncode == 0, sim.stderr
        truth: list[dict[str, Any]] = [json.loads(line) for line in truth_file.read_text().splitlines()]
        visited = sorted({line["stopped_at"] for line in truth if line["stopped_at"] is not None})
        # Each stop's record comes within a poll of the stop; give delivery its flush.
        dc.wait_until(lambda: len(dc.named("front_camera")) >= len(visited), 30, "a record per stop")
        records = dc.named("front_camera")
    assert len(visited) >= 5

    times = [line["t"] for line in truth]

    def truth_at(t: float) -> dict[str, Any]:
        return truth[max(bisect.bisect_right(times, t) - 1, 0)]

    demo = yaml.safe_load((REPO / "params" / "demos" / "qr_codes.yaml").read_text())
    standing_below = demo["measurement_server"]["ros__parameters"]["moving"]["speed_threshold"]
    labels = shelf_labels(warehouse_route())
    read_at: dict[int, list[dict[str, Any]]] = {}
    for record in records:
        state = truth_at(record["date"])
        # Only while standing, in front of a shelf label. A record is dated with its frame: a frame taken
        # before the poll that saw the robot stand (while it still crept) is not the one kept.
        assert abs(state["v"]) < standing_below and state["label_in_view"] is not None, (record["date"], state)
        read_at.setdefault(state["label_in_view"], []).append(record)
    # Once per stop, and every label of the route read in full: its QR code and its 1D code.
    assert sorted(read_at) == visited
    for waypoint, at_stop in read_at.items():
        assert len(at_stop) == 1, at_stop
        codes = {(c["type"], c["data"]) for c in at_stop[0]["inspected"]["barcode"]}
        label = labels[waypoint]
        assert ("QRCODE", label.qr) in codes
        assert ({"Code128": "CODE128", "EAN13": "EAN13"}[label.linear_format], label.linear) in codes
    # No frame saved twice: one image per record, each a readable JPEG, and nothing else saved.
    images = [Path(tmp_path / r["local_paths"]["inspected"]) for r in records]
    assert len(set(images)) == len(images)
    for image in images:
        assert cv2.imread(str(image)) is not None
    assert sorted((tmp_path / "var" / "dc" / "data").rglob("*.jpg")) == sorted(images)
    # The file destination has the same records.
    kept = [json.loads(line) for line in (tmp_path / "var/dc/records/qr_codes.jsonl").read_text().splitlines()]
    assert sorted(r["record_id"] for r in kept) == sorted(r["record_id"] for r in records)
