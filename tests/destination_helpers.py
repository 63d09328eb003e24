"""What the tests of several destination plugins share: sample records, a configured plugin, a PostgreSQL,
a run through the real sender and buffer."""

from __future__ import annotations

import contextlib
import logging
import secrets
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml

from dc_bringup.local_servers.postgres import PostgresServer
from dc_core.destination import Destination, OutgoingRecord
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

STAMP_NS = 1_677_668_906_045_817_000


def record(data: dict[str, Any], record_id: str = "r1", stamp_ns: int = STAMP_NS) -> OutgoingRecord:
    return OutgoingRecord(record_id, "/dc/measurement/uptime", stamp_ns, data)


def make(cls: type[Destination[Any]], name: str = "dest", **params: Any) -> Destination[Any]:
    plugin = cls(FakeContext(name=name), parse_params(cls.Params, params, f"destination_server.{name}"))
    plugin.on_configure()
    return plugin


def through_pipeline(
    tmp_path: Path,
    dest: Destination[Any],
    records: list[OutgoingRecord],
    until: Callable[[dict[str, Any]], bool],
    *,
    scheduler_cap: float = 0.2,
    timeout: float = 15.0,
) -> dict[str, Any]:
    """Deliver ``records`` to the configured ``dest`` through the real sender and buffer (short backoff)
    until ``until`` holds of the destination's metrics (counters, ``buffered``, ``health``); those metrics."""
    name = dest.context.name
    logger: Any = logging.getLogger(f"tests.through_pipeline.{name}")
    settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=scheduler_cap)
    pipeline = DeliveryPipeline(settings, {name: (dest, DestinationDeliveryParams())}, logger)
    dest.on_activate()
    pipeline.start()
    try:
        for rec in records:
            pipeline.submit(name, rec)
        deadline = time.monotonic() + timeout
        while not until(pipeline.metrics()[name]) and time.monotonic() < deadline:
            time.sleep(0.05)
        metrics = pipeline.metrics()[name]
    finally:
        pipeline.stop(0.5)
        dest.on_deactivate()
    assert until(metrics), metrics
    return metrics


def tls_refused(metrics: dict[str, Any]) -> bool:
    """The destination reported failing for a TLS verification (dc_destinations.health), records waiting."""
    health = metrics["health"]
    return health["state"] == "failing" and "TLS verification failed" in health.get("reason", "")


UPTIMES = [
    record({"date": 1677668906.045817, "time": 92395, "robot_name": "C3PO"}, "r1"),
    record({"date": 1677668911.7, "time": 92400, "robot_name": "C3PO"}, "r2"),
]


def forwarding_params(
    tmp_path: Path,
    destination: str,
    settings: dict[str, Any],
    *,
    measurement: str = "events",
    topic: str = "/robot/events",
) -> Path:
    """A parameter file for end-to-end tests: StringStamped forwards every record published on ``topic``
    (as ``dc pub`` does) to the destination ``destination`` (``settings``: its plugin and parameters),
    whose buffer lives in ``tmp_path`` and retries quickly (0.2 s doubling to 2 s)."""
    document = {
        "measurement_server": {
            "ros__parameters": {
                "measurement_plugins": [measurement],
                measurement: {
                    "plugin": "dc_measurements/StringStamped",
                    "topic": topic,
                    "timer_based": False,
                    "qos_depth": 1000,
                    "enable_validator": False,
                    "tags": [destination],
                },
            }
        },
        "destination_server": {
            "ros__parameters": {
                "flb": {
                    "storage_path": str(tmp_path / "buffer"),
                    "flush": 0.2,
                    "scheduler_base": 0.2,
                    "scheduler_cap": 2.0,
                },
                "destination_plugins": [destination],
                destination: {"inputs": [f"/dc/measurement/{measurement}"], **settings},
            }
        },
    }
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(document, sort_keys=False))
    return params


@contextlib.contextmanager
def running_postgres(prefix: str, password: str | None = None) -> Iterator[PostgresServer]:
    """A PostgreSQL of the test's own on loopback, running inside the block, its data removed after.

    Its folder is not under pytest's tmp_path: as root, PostgreSQL runs as user postgres, who
    cannot enter that.
    """
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    server = PostgresServer(folder, password=password or secrets.token_urlsafe(12))
    try:
        server.start()
        yield server
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)
