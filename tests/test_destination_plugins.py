"""Built-in destinations Stdout, File, Null and Rcl: what they write and how they fail (no ROS)."""

from __future__ import annotations

import csv
import json
import logging
import os
import stat
from pathlib import Path
from typing import Any

import pytest

from dc_core.destination import Destination, OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError, DcError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.config import DestinationCommonParams
from dc_destinations.file import File, FileParams
from dc_destinations.null import Null
from dc_destinations.rcl import Rcl
from dc_destinations.stdout import Stdout, StdoutParams

STAMP_NS = 1_677_668_906_045_817_000


def record(data: dict[str, Any], record_id: str = "r1", stamp_ns: int = STAMP_NS) -> OutgoingRecord:
    return OutgoingRecord(record_id, "/dc/measurement/uptime", stamp_ns, data)


def make(cls: type[Destination[Any]], name: str = "dest", **params: Any) -> Destination[Any]:
    plugin = cls(FakeContext(name=name), parse_params(cls.Params, params, f"destination_server.{name}"))
    plugin.on_configure()
    return plugin


def file_dest(tmp_path: Path, name: str = "disk", **params: Any) -> File:
    plugin = make(File, name, path=str(tmp_path), **params)
    assert isinstance(plugin, File)
    plugin.on_activate()
    return plugin


UPTIMES = [
    record({"date": 1677668906.045817, "time": 92395, "robot_name": "C3PO"}, "r1"),
    record({"date": 1677668911.7, "time": 92400, "robot_name": "C3PO"}, "r2"),
]


# -- Stdout ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["json", "json_lines", "json_stream", "plain"])
def test_stdout_prints_one_json_object_per_line(fmt: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = make(Stdout, format=fmt)
    assert out.send(UPTIMES) is None
    assert capsys.readouterr().out.splitlines() == [
        '{"date":1677668906.045817,"time":92395,"robot_name":"C3PO"}',
        '{"date":1677668911.7,"time":92400,"robot_name":"C3PO"}',
    ]


def test_stdout_keeps_non_ascii_readable(capsys: pytest.CaptureFixture[str]) -> None:
    make(Stdout).send([record({"name": "café ✓"})])
    assert capsys.readouterr().out == '{"name":"café ✓"}\n'


def test_stdout_msgpack_is_refused_at_configure() -> None:
    with pytest.raises(ConfigError) as info:
        parse_params(StdoutParams, {"format": "msgpack"}, "destination_server.flb_stdout")
    assert info.value.path == "destination_server.flb_stdout.format"


def test_stdout_closed_is_retryable(monkeypatch: pytest.MonkeyPatch) -> None:
    class Broken:
        def write(self, text: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            pass

    monkeypatch.setattr("sys.stdout", Broken())
    with pytest.raises(RetryableError, match="Broken pipe"):
        make(Stdout).send(UPTIMES)


# -- Null and Rcl ------------------------------------------------------------------------------------


def test_null_confirms_and_discards(capsys: pytest.CaptureFixture[str]) -> None:
    assert make(Null).send(UPTIMES) is None
    assert capsys.readouterr() == ("", "")


def test_rcl_logs_each_record_at_info() -> None:
    rcl = make(Rcl, "rcl")
    assert rcl.send(UPTIMES) is None
    logger = rcl.context.logger
    assert isinstance(logger, RecordingLogger)
    assert logger.lines == [("info", r.to_json()) for r in UPTIMES]


def test_rcl_works_with_a_standard_logger(caplog: pytest.LogCaptureFixture) -> None:
    rcl = Rcl(FakeContext(name="rcl", logger=logging.getLogger("dc.test.rcl")), None)  # type: ignore[arg-type]
    with caplog.at_level(logging.INFO, logger="dc.test.rcl"):
        rcl.send(UPTIMES[:1])
    assert caplog.messages == [UPTIMES[0].to_json()]


# -- File: formats -----------------------------------------------------------------------------------


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


# -- File: folders, configuration, failures ------------------------------------------------------------


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
    assert (p.path, p.file, p.format, p.mkdir) == ("$HOME/data", "", "json", True)


# -- documentation ---------------------------------------------------------------------------------------
# Every plugin's page is checked by tests/test_plugin_contract.py; what is particular to one is here.

STDOUT_PAGE = Path(__file__).resolve().parent.parent / "dc_destinations" / "stdout" / "README.md"


def test_stdout_doc_common_parameter_table_matches_the_code() -> None:
    text = STDOUT_PAGE.read_text()
    for info in describe_params(DestinationCommonParams):
        assert f"| `{info.name}` |" in text, f"stdout.md lacks a row for common parameter {info.name}"
