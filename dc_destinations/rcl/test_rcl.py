"""Rcl destination: every record logged at info."""

from __future__ import annotations

import logging

import pytest

from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.rcl import Rcl
from tests.destination_helpers import UPTIMES, make


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
