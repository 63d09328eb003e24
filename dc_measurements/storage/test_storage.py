"""Storage measurement, compared with os.statvfs."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dc_core.errors import PluginError
from dc_measurements.storage import Storage
from tests.measurement_helpers import assert_valid, configured


def test_storage_matches_statvfs_and_expands_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DC_TEST_STORAGE", str(tmp_path))
    record = configured(Storage, path="$DC_TEST_STORAGE").collect()
    assert_valid(Storage, record)
    fs = os.statvfs(tmp_path)
    capacity = fs.f_blocks * fs.f_frsize
    free = fs.f_bavail * fs.f_frsize  # available to the user, not f_bfree
    assert record["capacity"] == capacity
    # Other sessions write to the same disk: allow some drift between the two reads.
    assert record["free"] == pytest.approx(free, abs=64 * 1024**2)
    assert record["free_percent"] == pytest.approx(free / capacity * 100, abs=0.5)


def test_storage_rejects_unset_variable_and_missing_path(tmp_path: Path) -> None:
    with pytest.raises(PluginError, match="DC_TEST_UNSET_VARIABLE"):
        configured(Storage, path="$DC_TEST_UNSET_VARIABLE/data")
    with pytest.raises(PluginError, match="does not exist"):
        configured(Storage, path=str(tmp_path / "missing"))


def test_storage_publishes_nothing_while_the_path_is_gone(tmp_path: Path) -> None:
    mount = tmp_path / "usb"
    mount.mkdir()
    plugin = configured(Storage, path=str(mount))
    mount.rmdir()
    assert plugin.collect() is None
    mount.mkdir()
    assert plugin.collect() is not None
