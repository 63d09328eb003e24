"""Null destination: confirms and discards."""

from __future__ import annotations

import pytest

from dc_destinations.null import Null
from tests.destination_helpers import UPTIMES, make


def test_null_confirms_and_discards(capsys: pytest.CaptureFixture[str]) -> None:
    assert make(Null).send(UPTIMES) is None
    assert capsys.readouterr() == ("", "")
