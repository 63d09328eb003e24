"""File destination against a real file system: formats, folders, fsync, a full disk."""

from __future__ import annotations

import csv
import json
import os
import stat
from pathlib import Path
from typing import Any

import pytest

from dc_core.destination import RetryableError, SendOutcome
from dc_core.errors import ConfigError, DcError
from dc_core.params import parse_params
from dc_destinations.file import File, FileParams
from tests.destination_helpers import UPTIMES, make, record


def file_dest(tmp_path: Path, name: str = "disk", **params: Any) -> File:
    plugin = make(File, name, path=str(tmp_path), **params)
    assert isinstance(plugin, File)
    plugin.on_activate()
    return plugin


def test_file_default_is_json_lines_named_after_the_destination(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, "flb_file")
    assert dest.send(UPTIMES) is None
    assert dest.send(UPTIMES[:1]) is None
    lines = (tmp_path / "flb_file").read_text().splitlines()
    assert [json.loads(line) for line in lines] == [r.data for r in [*UPTIMES, UPTIMES[0]]]


def test_file_plain_is_json_lines_too(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, file="uptime", format="plain")
    dest.send(UPTIMES)
    assert (tmp_path / "uptime").read_text() == "".join(r.to_json() + "\n" for r in UPTIMES)


def test_file_csv_header_from_first_record_and_nested_values_as_json(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, file="data.csv", format="csv")
    batch = [
        record({"date": 1.5, "name": "cpu", "cpus": [1, 2], "ok": True, "note": "a,b"}),
        record({"date": 2.5, "name": "mem", "ok": False, "note": None}),  # missing key: empty cell
    ]
    assert dest.send(batch) is None
    assert dest.send([record({"name": "x", "date": 3.0})]) is None  # other key order: same columns
    rows = list(csv.reader((tmp_path / "data.csv").open(newline="")))
    assert rows == [
        ["date", "name", "cpus", "ok", "note"],
        ["1.5", "cpu", "[1,2]", "true", "a,b"],
        ["2.5", "mem", "", "false", ""],
        ["3.0", "x", "", "", ""],
    ]


def test_file_csv_record_with_unknown_columns_is_rejected_not_lost(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, file="data.csv", format="csv")
    outcome = dest.send([record({"a": 1}), record({"a": 2, "b": 3}), record({"a": 4})])
    assert isinstance(outcome, SendOutcome)
    assert list(outcome.reject) == [1]
    assert "b" in outcome.reject[1]
    assert (tmp_path / "data.csv").read_text() == "a\n1\n4\n"


def test_file_csv_appends_under_the_existing_header_after_a_restart(tmp_path: Path) -> None:
    first = file_dest(tmp_path, file="data.csv", format="csv", delimiter=";")
    first.send([record({"x": 1, "y": 2})])
    first.on_deactivate()
    second = file_dest(tmp_path, file="data.csv", format="csv", delimiter=";")
    second.send([record({"y": 4, "x": 3})])
    assert (tmp_path / "data.csv").read_text() == "x;y\n1;2\n3;4\n"


def test_file_ltsv(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, file="d.ltsv", format="ltsv")
    dest.send([record({"date": 1.5, "tags": ["a"], "name": "cpu"})])
    assert (tmp_path / "d.ltsv").read_text() == 'date:1.5\ttags:["a"]\tname:cpu\n'


def test_file_out_file_is_fluent_bits_layout(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, "flb_file", format="out_file")
    dest.send([record({"time": 1})])
    assert (tmp_path / "flb_file").read_text() == 'flb_file: [1677668906.045817000, {"time":1}]\n'


def test_file_template(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, file="t", format="template", template="{time} {name}={value} {missing}")
    dest.send([record({"name": "cpu", "value": {"avg": 3}})])
    assert (tmp_path / "t").read_text() == '1677668906.045817000 cpu={"avg":3} \n'


def test_file_mkdir_creates_missing_folders(tmp_path: Path) -> None:
    folder = tmp_path / "a" / "b"
    dest = file_dest(folder, file="out")
    assert folder.is_dir()
    assert stat.S_IMODE(folder.stat().st_mode) & 0o700 == 0o700
    dest.send(UPTIMES[:1])
    assert (folder / "out").exists()


def test_file_without_mkdir_retries_until_the_folder_exists(tmp_path: Path) -> None:
    folder = tmp_path / "later"
    dest = file_dest(folder, file="out", mkdir=False)
    with pytest.raises(RetryableError, match="No such file or directory"):
        dest.send(UPTIMES[:1])
    folder.mkdir()
    assert dest.send(UPTIMES[:1]) is None
    assert (folder / "out").read_text() == UPTIMES[0].to_json() + "\n"


def test_file_path_expands_environment_variables(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DC_TEST_DATA", str(tmp_path))
    dest = make(File, "disk", path="$DC_TEST_DATA/sub")
    assert isinstance(dest, File)
    assert dest.file_path == str(tmp_path / "sub" / "disk")


def test_file_unset_variable_fails_configure_with_the_yaml_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DC_TEST_UNSET", raising=False)
    with pytest.raises(ConfigError) as info:
        make(File, "disk", path="$DC_TEST_UNSET/x")
    assert info.value.path == "destination_server.disk.path"


@pytest.mark.parametrize(
    ("params", "message"),
    [({"file": "a/b"}, "without '/'"), ({"format": "csv", "delimiter": "::"}, "one character")],
)
def test_file_configure_errors(params: dict[str, Any], message: str) -> None:
    with pytest.raises(DcError, match=message):
        make(File, "disk", path="/tmp", **params)


@pytest.mark.skipif(not os.access("/dev/full", os.W_OK), reason="needs a writable /dev/full")
def test_file_disk_full_is_retryable() -> None:
    # /dev/full answers every write with ENOSPC: a real full disk, seen through the same system calls.
    dest = make(File, "full", path="/dev", file="full", mkdir=False)
    with pytest.raises(RetryableError, match="No space left on device"):
        dest.send(UPTIMES)


def test_file_failed_write_leaves_no_partial_batch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    dest = file_dest(tmp_path, file="out")
    dest.send(UPTIMES[:1])
    real_write = os.write

    def write_half_then_fail(fd: int, data: Any) -> int:
        # A disk filling up mid-batch: part of the bytes land, then ENOSPC.
        monkeypatch.setattr(os, "write", fail)
        return real_write(fd, bytes(data[: len(data) // 2]))

    def fail(fd: int, data: Any) -> int:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "write", write_half_then_fail)
    with pytest.raises(RetryableError, match="No space left on device"):
        dest.send(UPTIMES)
    monkeypatch.setattr(os, "write", real_write)
    assert (tmp_path / "out").read_text() == UPTIMES[0].to_json() + "\n"
    dest.send(UPTIMES)  # the retry
    assert (tmp_path / "out").read_text() == "".join(r.to_json() + "\n" for r in [UPTIMES[0], *UPTIMES])


def test_file_is_fsynced_before_send_returns(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[int] = []
    real_fsync = os.fsync

    def spy(fd: int) -> None:
        synced.append(fd)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", spy)
    dest = file_dest(tmp_path, file="out")
    synced.clear()
    dest.send(UPTIMES)
    assert synced, "send() returned without fsync: a confirmed record could be lost in a power cut"


def test_file_rotated_away_starts_a_new_file(tmp_path: Path) -> None:
    dest = file_dest(tmp_path, file="out")
    dest.send(UPTIMES[:1])
    (tmp_path / "out").rename(tmp_path / "out.1")
    dest.send(UPTIMES[1:])
    assert (tmp_path / "out.1").read_text() == UPTIMES[0].to_json() + "\n"
    assert (tmp_path / "out").read_text() == UPTIMES[1].to_json() + "\n"


def test_params_defaults() -> None:
    p = parse_params(FileParams, {}, "x")
    assert (p.path, p.file, p.format, p.mkdir, p.file_mode) == ("$HOME/data", "", "json", True, "0600")


@pytest.fixture
def umask(request: pytest.FixtureRequest) -> Any:
    previous = os.umask(request.param)
    yield request.param
    os.umask(previous)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.parametrize("umask", [0o022, 0o077], indirect=True)
def test_file_is_created_0600_in_0700_folders_whatever_the_umask(tmp_path: Path, umask: int) -> None:
    dest = file_dest(tmp_path / "a" / "b", file="out")
    dest.send(UPTIMES[:1])
    assert mode(tmp_path / "a" / "b" / "out") == 0o600
    assert mode(tmp_path / "a") == mode(tmp_path / "a" / "b") == 0o700
    # A file rotated away is started again with the same mode.
    (tmp_path / "a" / "b" / "out").rename(tmp_path / "a" / "b" / "out.1")
    dest.send(UPTIMES[1:])
    assert mode(tmp_path / "a" / "b" / "out") == 0o600


@pytest.mark.parametrize("umask", [0o077], indirect=True)
def test_file_mode_gives_a_group_read_and_its_folders_a_way_in(tmp_path: Path, umask: int) -> None:
    dest = file_dest(tmp_path / "shared", file="out", file_mode="0640")
    dest.send(UPTIMES[:1])
    assert mode(tmp_path / "shared" / "out") == 0o640
    assert mode(tmp_path / "shared") == 0o750


def test_file_keeps_the_mode_of_a_file_it_did_not_create(tmp_path: Path) -> None:
    # Made by logrotate or an operator, with the mode they chose: DC appends, it does not chmod.
    (tmp_path / "out").write_text("")
    (tmp_path / "out").chmod(0o644)
    dest = file_dest(tmp_path, file="out")
    dest.send(UPTIMES[:1])
    assert mode(tmp_path / "out") == 0o644
    assert (tmp_path / "out").read_text() == UPTIMES[0].to_json() + "\n"


@pytest.mark.parametrize("value", [416, "rw-r-----", "0778"])
def test_file_mode_that_is_not_a_quoted_octal_mode_fails_configure_with_the_yaml_path(value: Any) -> None:
    with pytest.raises(ConfigError, match=r'quoted octal string, e\.g\. "0600"') as info:
        make(File, "disk", path="/tmp", file_mode=value)
    assert info.value.path == "destination_server.disk.file_mode"
