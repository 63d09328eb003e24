"""Stdout destination: what it prints, and its page's table of common parameters."""

from __future__ import annotations

from pathlib import Path

import pytest

from dc_core.destination import RetryableError
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_destinations.config import DestinationCommonParams
from dc_destinations.stdout import Stdout, StdoutParams
from tests.destination_helpers import UPTIMES, make, record


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


STDOUT_PAGE = Path(__file__).resolve().parent / "README.md"


def test_stdout_doc_common_parameter_table_matches_the_code() -> None:
    text = STDOUT_PAGE.read_text()
    for info in describe_params(DestinationCommonParams):
        assert f"| `{info.name}` |" in text, f"stdout.md lacks a row for common parameter {info.name}"
