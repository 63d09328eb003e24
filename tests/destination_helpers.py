"""What the tests of several destination plugins share: sample records, a configured plugin."""

from __future__ import annotations

from typing import Any

from dc_core.destination import Destination, OutgoingRecord
from dc_core.params import parse_params
from dc_core.testing import FakeContext

STAMP_NS = 1_677_668_906_045_817_000


def record(data: dict[str, Any], record_id: str = "r1", stamp_ns: int = STAMP_NS) -> OutgoingRecord:
    return OutgoingRecord(record_id, "/dc/measurement/uptime", stamp_ns, data)


def make(cls: type[Destination[Any]], name: str = "dest", **params: Any) -> Destination[Any]:
    plugin = cls(FakeContext(name=name), parse_params(cls.Params, params, f"destination_server.{name}"))
    plugin.on_configure()
    return plugin


UPTIMES = [
    record({"date": 1677668906.045817, "time": 92395, "robot_name": "C3PO"}, "r1"),
    record({"date": 1677668911.7, "time": 92400, "robot_name": "C3PO"}, "r2"),
]
