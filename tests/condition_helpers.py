"""What the tests of several condition plugins share: a configured condition, the expected outcome of a sample."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest

from dc_core.condition import Condition
from dc_core.params import parse_params
from dc_core.testing import FakeContext

PATH = "measurement_server.c"


@dataclass(frozen=True)
class Inactive:
    """Expected outcome: evaluate raises one of the documented errors, its message containing ``reason``."""

    reason: str


def configured(cls: type[Condition[Any]], params: dict[str, Any]) -> Condition[Any]:
    condition = cls(FakeContext(name="c"), parse_params(cls.Params, params, PATH))
    condition.on_configure()
    return condition


def check(condition: Condition[Any], sample: Any, expected: bool | Inactive) -> None:
    if isinstance(expected, Inactive):
        with pytest.raises((LookupError, TypeError, ValueError)) as caught:
            condition.evaluate(sample)
        assert expected.reason in str(caught.value)
    else:
        assert condition.evaluate(sample) is expected


BARCODES = {"inspected": {"barcode": [{"data": "QR-1", "ok": True}, {"data": "QR-2", "ok": False}]}}
