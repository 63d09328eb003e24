"""The disk budget over DC's saved files and the buffer (dc_destinations.saved_files, disk_budget).

Real files on disk, the real pipeline, the real MinIO destination against SeaweedFS and FilesMetrics
against PostgreSQL (both started here, once for the module); the free-space floor on a small real
tmpfs that another process fills. Every test ends in: files delivered + evicted (counted) = produced.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.cli import _print_delivery
from dc_bringup.local_servers.postgres import PostgresServer
from dc_bringup.local_servers.postgres import missing_reason as postgres_missing
from dc_bringup.local_servers.seaweedfs import SeaweedS3Server
from dc_bringup.local_servers.seaweedfs import missing_reason as seaweed_missing
from dc_core.destination import Destination, OutgoingRecord, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.buffer import SqliteBuffer
from dc_destinations.config import parse_destination_server
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.disk_budget import FileCandidate, Step, budget_plan, queue_classes
from dc_destinations.links import OnlyWhenParams
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.destination_helpers import running_postgres
from tests.fault_helpers import tmpfs

LOG = logging.getLogger("tests.test_disk_budget")
PASSWORD = "pg-Budget-Secret-31"
KB = 1024


def poll(check: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def saved_record(path: Path, measurement: str, run_id: str = "r1") -> OutgoingRecord:
    rid = new_record_id()
    kind = path.suffix.lstrip(".")
    data = {
        "name": measurement,
        "run_id": run_id,
        "robot_name": "C3PO",
        "local_paths": {kind: str(path)},
        "remote_paths": {"minio": {kind: f"C3PO/{measurement}/{path.name}"}},
        "record_id": rid,
    }
    return OutgoingRecord(rid, f"/dc/measurement/{measurement}", time.time_ns(), data)


def save(folder: Path, measurement: str, n: int, size: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{measurement}-{n:03}.{'mcap' if measurement == 'incident' else 'jpeg'}"
    path.write_bytes(bytes([n % 251]) * size)
    return path


def started(tmp_path: Path, destinations: dict[str, Any], roots: list[Path], **flb: Any) -> DeliveryPipeline:
    """A pipeline with its buffer in ``tmp_path``, started, its saved files in ``roots`` (and the destinations')."""
    settings = DeliveryParams(storage_path=str(tmp_path / "buffer"), flush=0.05, http_server=False, **flb)
    pipeline = DeliveryPipeline(settings, destinations, LOG, saved_files_roots=[str(root) for root in roots])
    pipeline.start()
    return pipeline


# -- the plan, pure ---------------------------------------------------------------------------------


def test_the_plan_gives_up_delivered_files_first_then_by_retention_priority_keeping_run_ends() -> None:
    def f(path: str, priority: int, *, delivered: bool = False, protected: bool = False, seq: int = 0) -> FileCandidate:
        return FileCandidate(path, 100, priority, delivered, protected, seq)

    files = [
        f("cam-first", 0, protected=True, seq=1),
        f("cam-2", 0, seq=2),
        f("cam-3", 0, seq=3),
        f("incident-sent", 10, delivered=True, seq=4),
        f("incident-only", 10, seq=5),
        f("cam-last", 0, protected=True, seq=6),
    ]
    records = queue_classes({"images": 150, "health": 100}, {"images": 0, "health": 10})
    plan = budget_plan(records, files, 10_000)
    assert plan == [
        Step("file", "incident-sent", 100),  # safe elsewhere, whatever its priority
        Step("file", "cam-2", 100),
        Step("file", "cam-3", 100),
        Step("records", "0", 150, (("images", None),)),
        Step("file", "cam-first", 100),  # the run's ends, last of their priority
        Step("file", "cam-last", 100),
        Step("file", "incident-only", 100),  # the only copy of the higher priority: nothing lower is left
        Step("records", "10", 100, (("health", None),)),
    ]
    assert budget_plan(records, files, 150) == plan[:2]
    # Under the free-space floor only files go: freed records' pages stay with SQLite.
    assert all(step.kind == "file" for step in budget_plan([], files, 10_000))


@pytest.mark.parametrize(
    ("flb", "path", "says"),
    [
        ({"disk_budget": "0"}, "destination_server.flb.disk_budget", "would evict everything"),
        ({"disk_budget": "0%"}, "destination_server.flb.disk_budget", "would evict everything"),
        ({"disk_budget": "100%"}, "destination_server.flb.disk_budget", "below 100%"),
        ({"disk_budget": "ten%"}, "destination_server.flb.disk_budget", "percentage"),
        ({"disk_budget": "512k"}, "destination_server.flb.disk_budget", "smaller than one batch"),
        ({"disk_budget": "50M", "disk_budget_mb": 50}, "destination_server.flb.disk_budget", "not both"),
        ({"disk_free_floor": "0"}, "destination_server.flb.disk_free_floor", "would never act"),
    ],
)
def test_bad_budgets_are_configure_errors_naming_the_key(flb: dict[str, Any], path: str, says: str) -> None:
    section = {
        "destination_plugins": ["d"],
        "flb": flb,
        "d": {"plugin": "dc_destinations/Null", "inputs": ["/dc/measurement/x"]},
    }
    with pytest.raises(ConfigError) as raised:
        parse_destination_server(section)
    assert raised.value.path == path and says in raised.value.message


# -- saved files with MinIO and FilesMetrics ----------------------------------------------------------


@pytest.fixture(scope="module")
def pg() -> Iterator[PostgresServer]:
    if postgres_missing():
        pytest.skip(f"no local server: {postgres_missing()}")
    with running_postgres("dc-budget-pg-", PASSWORD) as server:
        yield server


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    if seaweed_missing():
        pytest.skip(f"no local server: {seaweed_missing()}")
    server = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    server.start()
    yield server
    server.stop(timeout=3.0)


def store_settings(s3: SeaweedS3Server) -> dict[str, Any]:
    s = s3.settings()
    return {
        "endpoint": f"127.0.0.1:{s3.port}",
        "use_ssl": False,
        "access_key_id": s["aws_access_key_id"],
        "secret_access_key": s["aws_secret_access_key"],
        "bucket": s3.bucket,
        "src_fields": ["local_paths.jpeg", "local_paths.mcap"],
        "upload_fields": ["remote_paths.minio.jpeg", "remote_paths.minio.mcap"],
    }


def minio_destination(s3: SeaweedS3Server, kind: type[Any] | None = None) -> Any:
    """The MinIO destination of SeaweedFS's bucket, configured and active (``kind``: a subclass of MinIO)."""
    from dc_destinations.minio import MinIO, MinIOParams

    params = {**store_settings(s3), "allowed_roots": [tempfile.gettempdir()], "complete_after": 0.0}
    minio = (kind or MinIO)(
        FakeContext(name="minio", logger=RecordingLogger()),
        parse_params(MinIOParams, params, "destination_server.minio"),
    )
    minio.on_configure()
    minio.on_activate()
    return minio


def file_destinations(
    pg: PostgresServer, s3: SeaweedS3Server, held: OnlyWhenParams, table: str = "budget_files"
) -> dict[str, Any]:
    from dc_destinations.files_metrics import FilesMetrics, FilesMetricsParams

    store, roots = store_settings(s3), [tempfile.gettempdir()]
    minio = minio_destination(s3)
    files = FilesMetrics(
        FakeContext(name="files", logger=RecordingLogger()),
        parse_params(
            FilesMetricsParams,
            {
                "file_storage": ["minio"],
                "minio": store,
                "missing_wait": 0.0,
                "allowed_roots": roots,
                "pgsql": {**pg.settings(), "table": table, "connect_timeout": 2},
            },
            "destination_server.files",
        ),
    )
    files.on_configure()
    files.on_activate()
    params = DestinationDeliveryParams(only_when=held, batch_size=20)
    return {"minio": (minio, params), "files": (files, params)}


def test_saved_files_are_evicted_by_value_counted_and_shown_in_files_metrics(
    pg: PostgresServer,
    s3: SeaweedS3Server,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A robot off its dock saves 30 camera images and 6 incident recordings against a 1 MB budget:
    the oldest images go (not the run's first and last), no recording; at the dock the rest is
    uploaded and verified, and FilesMetrics' rows say which files were evicted. Then, over the
    budget again, delivered files go before any new recording."""
    import psycopg

    save_dir = tmp_path / "save"
    settings = DeliveryParams(
        storage_path=str(tmp_path / "buffer"),
        flush=0.05,
        scheduler_base=0.05,
        scheduler_cap=0.2,
        http_port=0,
        disk_budget="1M",
        keep_run_ends=1,
        retention_priorities={"incident": 10, "camera": 0},
    )
    pipeline = DeliveryPipeline(settings, file_destinations(pg, s3, OnlyWhenParams(conditions=["docked"])), LOG)
    pipeline.start()
    pipeline.set_condition("docked", False)  # off the dock
    produced: dict[str, list[Path]] = {"camera": [], "incident": []}

    def produce(measurement: str, count: int) -> None:
        for _ in range(count):
            path = save(save_dir, measurement, len(produced[measurement]), 40 * KB)
            produced[measurement].append(path)
            record = saved_record(path, measurement)
            pipeline.submit_record([("minio", record), ("files", record)])

    def files_of(measurement: str) -> dict[str, Any]:
        return dict(pipeline.status_document()["saved_files"]["measurements"][measurement])

    def within_budget() -> bool:
        document = pipeline.status_document()
        buffered = sum(m["buffered_bytes"] or 0 for m in document["destinations"].values())
        return int(document["saved_files"]["bytes"]) + buffered <= 1024 * 1024

    try:
        with caplog.at_level(logging.WARNING):
            for _ in range(6):  # an incident now and then among the images
                produce("camera", 5)
                produce("incident", 1)
            assert pipeline.flush_intake(10)
            poll(lambda: files_of("camera")["produced"] == 30 and within_budget(), 30, "the files within the budget")
        camera, incident = files_of("camera"), files_of("incident")
        assert incident["evicted"] == 0 and incident["kept"] == 6
        assert camera["evicted"] == camera["evicted_unsent"] > 0
        first, last = produced["camera"][0], produced["camera"][-1]
        assert first.exists() and last.exists()  # keep_run_ends: 1
        gone = [p for p in produced["camera"] if not p.exists()]
        assert len(gone) == camera["evicted"]
        # The oldest images went first (after the run's first one).
        assert gone == produced["camera"][1 : 1 + len(gone)]
        assert "saved files evicted to keep DC within flb.disk_budget" in caplog.text
        metrics = pipeline.metrics()
        assert metrics["minio"]["files_evicted"] == metrics["files"]["files_evicted"] == len(gone)
        shown(pipeline, capsys, len(gone))
        assert f'dc_delivery_files_evicted_total{{destination="minio"}} {len(gone)}' in pipeline.prometheus()

        pipeline.set_condition("docked", True)

        def settled() -> bool:
            m = pipeline.metrics()
            return all(m[d]["buffered"] == 0 and m[d]["received"] == 36 for d in ("minio", "files"))

        poll(settled, 60, "the backlog uploaded and tracked")
        metrics = pipeline.metrics()
        # MinIO's records naming evicted files were taken out of its queue, counted evicted.
        assert metrics["minio"]["sent"] + metrics["minio"]["evicted"] == 36 and metrics["minio"]["evicted"] == len(gone)
        # FilesMetrics recorded them: every record sent, the evicted files' rows say evicted.
        assert metrics["files"]["sent"] == 36 and metrics["files"]["evicted"] == 0
        kept = [p for paths in produced.values() for p in paths if p.exists()]
        stored = set(s3.objects("C3PO/"))
        assert stored == {f"C3PO/{p.name.split('-')[0]}/{p.name}" for p in kept}
        with psycopg.connect(**pg_connect(pg)) as connection:
            rows = dict(connection.execute("SELECT local_path, evicted FROM budget_files WHERE uploaded OR evicted"))
        assert {p for p, evicted in rows.items() if evicted} == {str(p) for p in gone}
        assert {p for p, evicted in rows.items() if not evicted} == {str(p) for p in kept}

        def accounted() -> bool:  # the ledger takes the confirmations in at its next tick
            return all(
                (c := files_of(m))["delivered"] + c["evicted_unsent"] == c["produced"] == len(produced[m])
                for m in ("camera", "incident")
            )

        poll(accounted, 10, "every file delivered or counted evicted")

        # Held again, new recordings over the budget: the delivered files go, not the new only copies.
        pipeline.set_condition("docked", False)
        produce("incident", 8)
        assert pipeline.flush_intake(10)
        poll(lambda: files_of("incident")["produced"] == 14 and within_budget(), 30, "within the budget again")
        assert all(p.exists() for p in produced["incident"][6:])
        camera_after, incident_after = files_of("camera"), files_of("incident")
        assert camera_after["evicted"] > camera["evicted"]  # delivered images went
        assert camera_after["evicted_unsent"] == camera["evicted_unsent"]
        assert incident_after["evicted_unsent"] == 0
        pipeline.set_condition("docked", True)
        poll(
            lambda: all(m["buffered"] == 0 and m["received"] == 44 for m in pipeline.metrics().values()),
            60,
            "the new recordings uploaded and tracked",
        )
        poll(accounted, 10, "every file delivered or counted evicted")
    finally:
        pipeline.stop(0.5)


def test_a_file_evicted_after_files_metrics_recorded_it_has_its_row_say_so(
    pg: PostgresServer, s3: SeaweedS3Server, tmp_path: Path
) -> None:
    """Images uploaded, verified and recorded in files_metrics, then evicted to make room for newer
    ones (delivered files go first): their rows say evicted, no longer on the filesystem, still
    uploaded; the kept ones' rows are unchanged. Every file delivered: produced = delivered."""
    import psycopg

    destinations = file_destinations(pg, s3, OnlyWhenParams(), "evicted_after")
    pipeline = started(tmp_path, destinations, [], disk_budget="1M", scheduler_base=0.05)
    produced: list[Path] = []

    def produce(count: int) -> None:
        for _ in range(count):
            produced.append(save(tmp_path / "save", "camera", len(produced), 40 * KB))
            record = saved_record(produced[-1], "camera")
            pipeline.submit_record([("minio", record), ("files", record)])

    def camera() -> dict[str, Any]:
        return dict(pipeline.status_document()["saved_files"]["measurements"].get("camera", {}))

    def rows() -> dict[str, tuple[bool, bool, bool]]:
        with psycopg.connect(**pg_connect(pg)) as connection:
            found = connection.execute("SELECT local_path, uploaded, on_filesystem, evicted FROM evicted_after")
            return {path: (uploaded, on_fs, evicted) for path, uploaded, on_fs, evicted in found}

    try:
        produce(15)  # 600 kB: within the budget
        assert pipeline.flush_intake(10)
        poll(lambda: camera().get("delivered") == 15, 60, "the first images uploaded and recorded")
        assert rows() == {str(p): (True, True, False) for p in produced}
        produce(15)  # 1.2 MB: the oldest delivered images go
        assert pipeline.flush_intake(10)

        def settled() -> bool:
            gone = {str(p) for p in produced if not p.exists()}
            found = rows()
            return (
                camera().get("delivered") == 30
                and len(found) == 30
                and bool(gone)
                and all(found[p] == ((True, False, True) if p in gone else (True, True, False)) for p in found)
            )

        poll(settled, 60, "the evicted files' rows saying so")
        gone = [p for p in produced if not p.exists()]
        assert gone == produced[: len(gone)]
        counts, metrics = camera(), pipeline.metrics()
        assert counts["produced"] == counts["delivered"] == 30 and counts["evicted"] == len(gone)
        assert counts["evicted_unsent"] == 0
        assert metrics["minio"]["sent"] == metrics["files"]["sent"] == 30
        assert metrics["files"]["failed"] == 0
    finally:
        pipeline.stop(0.5)


def test_a_record_whose_file_is_evicted_while_it_is_in_send_is_counted_evicted(
    s3: SeaweedS3Server, tmp_path: Path
) -> None:
    """MinIO has a camera image's record in send() when a recording (retention priority 10) pushes DC
    over its budget and the image, the only lower-priority copy, is evicted: MinIO finds no file.
    The record is counted evicted, not dead-lettered: received = sent + evicted, and for the image
    produced = delivered + evicted_unsent."""
    import threading

    from dc_destinations.minio import MinIO

    in_send, evicted = threading.Event(), threading.Event()

    class EvictedInSend(MinIO):
        def send(self, batch: Any) -> SendOutcome | None:
            in_send.set()
            assert evicted.wait(60), "the file was not evicted"
            return super().send(batch)

    minio = minio_destination(s3, EvictedInSend)
    destinations = {
        "minio": (minio, DestinationDeliveryParams(batch_size=1)),
        "records": (Collecting(), DestinationDeliveryParams()),
    }
    pipeline = started(
        tmp_path, destinations, [tmp_path / "save"], disk_budget="1M", retention_priorities={"incident": 10}
    )

    def counts(measurement: str) -> dict[str, Any]:
        return dict(pipeline.status_document()["saved_files"]["measurements"].get(measurement, {}))

    try:
        # Its own object key: none of the other tests' objects may stand in for the file.
        image = save(tmp_path / "save", "in-send", 0, 600 * KB)
        pipeline.submit("minio", saved_record(image, "in-send"))
        assert pipeline.flush_intake(10)
        assert in_send.wait(30), "MinIO was not sent the image's record"
        poll(lambda: counts("in-send").get("produced") == 1, 30, "the image noted")
        recording = save(tmp_path / "save", "incident", 0, 600 * KB)
        pipeline.submit("records", saved_record(recording, "incident"))
        assert pipeline.flush_intake(10)
        poll(lambda: counts("in-send").get("evicted") == 1, 30, "the image evicted")
        evicted.set()
        poll(lambda: pipeline.metrics()["minio"]["buffered"] == 0, 30, "MinIO's queue emptied")
        metrics = pipeline.metrics()["minio"]
        assert recording.exists() and not image.exists()
        assert (metrics["received"], metrics["sent"], metrics["evicted"], metrics["dead_lettered"]) == (1, 0, 1, 0)
        image_counts = counts("in-send")
        assert image_counts["produced"] == image_counts["delivered"] + image_counts["evicted_unsent"] == 1
        assert pipeline.metrics()["minio"]["files_evicted"] == 1
    finally:
        evicted.set()
        pipeline.stop(0.5)


def shown(pipeline: DeliveryPipeline, capsys: pytest.CaptureFixture[str], evicted: int) -> None:
    """What `dc status` and the dashboard's Health page (from the real metrics endpoint) say meanwhile."""
    from dc_bringup.cli import _print_delivery
    from dc_dashboard.health import read
    from dc_dashboard.pages import health

    _print_delivery(pipeline.status_document(), wide=False)
    out = capsys.readouterr().out
    assert (
        f"destination minio: {evicted} records and {evicted} saved files evicted unsent by the disk budget" not in out
    )
    assert f"destination minio: 0 records and {evicted} saved files evicted unsent by the disk budget" in out
    assert "destination minio held: condition docked is false" in out
    assert f"camera (retention_priority 0): produced 30, delivered 0, evicted {evicted} ({evicted} unsent)" in out
    assert "incident (retention_priority 10): produced 6, delivered 0, evicted 0 (0 unsent), kept 6" in out

    address = pipeline.http_address
    assert address is not None
    server = read("robot", f"http://{address[0]}:{address[1]}/api/v1/metrics")
    assert not server.error
    page = health([server], {}, [], [], [], now=time.time())
    minio = page.split("<tr><td>minio</td>")[1].split("</tr>")[0]
    assert f"<td class=num>0 + {evicted} files</td><td class=held>held: condition docked is false</td>" in minio
    assert (
        "robot: destination minio held: condition docked is false; its backlog waits in the buffer: 36 records" in page
    )
    camera = page.split("<tr><td>camera</td>")[1].split("</tr>")[0]
    assert camera.startswith(
        f"<td class=num>0</td><td class=num>30</td><td class=num>0</td><td class=num>{evicted}</td>"
    )


def pg_connect(pg: PostgresServer) -> dict[str, Any]:
    return {
        "host": "127.0.0.1",
        "port": pg.port,
        "user": pg.user,
        "password": PASSWORD,
        "dbname": pg.database,
        "autocommit": True,
    }


# -- the free-space floor, on a small real filesystem ----------------------------------------------------


class Collecting(Destination[None]):
    def __init__(self) -> None:
        super().__init__(FakeContext(name="records"), None)
        self.received: list[OutgoingRecord] = []

    def send(self, batch: list[OutgoingRecord]) -> SendOutcome | None:  # type: ignore[override]
        self.received.extend(batch)
        return None


def test_a_disk_filled_by_another_process_is_given_back_by_the_same_rules(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """On an 8 MB filesystem, a budget of 25 % holds 1.25 MB of saved files; then another process
    writes 3.5 MB there: free space falls under the 40 % floor and DC evicts images, oldest first,
    never a recording, until the floor holds. A file larger than the whole budget is said."""
    with tmpfs(tmp_path / "disk", "8m") as disk:
        settings = DeliveryParams(
            storage_path=str(disk / "buffer"),
            flush=0.05,
            http_server=False,
            disk_budget="25%",
            disk_free_floor="40%",
            retention_priorities={"incident": 10},
        )
        sink = Collecting()
        save_dir = disk / "save"
        pipeline = DeliveryPipeline(
            settings, {"records": (sink, DestinationDeliveryParams())}, LOG, saved_files_roots=[str(save_dir)]
        )
        pipeline.start()
        produced: dict[str, list[Path]] = {"camera": [], "incident": []}

        def produce(measurement: str, count: int, size: int = 50 * KB) -> None:
            for _ in range(count):
                path = save(save_dir, measurement, len(produced[measurement]), size)
                produced[measurement].append(path)
                pipeline.submit("records", saved_record(path, measurement))

        def counts(measurement: str) -> dict[str, Any]:
            return dict(pipeline.status_document()["saved_files"]["measurements"][measurement])

        def free() -> int:
            stats = os.statvfs(disk)
            return stats.f_bavail * stats.f_frsize

        try:
            produce("camera", 20)
            produce("incident", 5)
            assert pipeline.flush_intake(10)
            poll(lambda: counts("camera")["produced"] == 20 and counts("incident")["produced"] == 5, 30, "files noted")
            time.sleep(1.1)  # two ticks of the budget: nothing to evict within it (an absence: no event to await)
            assert counts("camera")["evicted"] == 0 and counts("incident")["evicted"] == 0
            floor = int(0.4 * 8 * 1024 * 1024)
            with caplog.at_level(logging.WARNING):
                filler = disk / "other" / "filler.bin"
                filler.parent.mkdir()
                subprocess.run(
                    [sys.executable, "-c", f"open({str(filler)!r}, 'wb').write(b'x' * {3584 * KB})"], check=True
                )
                # (Not checked under the floor here: DC's next tick may already have given it back.)
                poll(lambda: free() >= floor and counts("camera")["evicted"] > 0, 30, "the floor given back")
            camera, incident = counts("camera"), counts("incident")
            assert incident["evicted"] == 0 and all(p.exists() for p in produced["incident"])
            gone = [p for p in produced["camera"] if not p.exists()]
            assert len(gone) == camera["evicted"] > 0 and gone == produced["camera"][: len(gone)]
            assert filler.exists() and filler.stat().st_size == 3584 * KB  # not DC's to touch
            # No destination carries these files: each was the only copy, evicted unsent and counted.
            for measurement, paths in produced.items():
                c = counts(measurement)
                assert c["produced"] == len(paths) == c["kept"] + c["evicted_unsent"]
            assert "saved files evicted" in caplog.text

            # A file larger than the whole budget (25 % of 8 MB) is said, clearly.
            filler.unlink()
            with caplog.at_level(logging.ERROR):
                produce("camera", 1, size=2200 * KB)
                poll(lambda: "larger than the whole disk budget" in caplog.text, 30, "the error")
            assert "raise flb.disk_budget above the largest file" in caplog.text
        finally:
            pipeline.stop(0.5)


def test_the_floor_watches_the_save_folders_filesystem_too(tmp_path: Path) -> None:
    """The buffer on a large disk, the save folder on an 8 MB tmpfs that another process fills under a
    3 MB floor: DC evicts the oldest images there, never a recording, and not an older image saved on
    the buffer's disk (evicting it would free nothing where space is short)."""
    with tmpfs(tmp_path / "disk", "8m") as disk:
        save_dir, elsewhere = disk / "save", tmp_path / "save"
        pipeline = started(
            tmp_path,
            {"records": (Collecting(), DestinationDeliveryParams())},
            [elsewhere, save_dir],
            disk_free_floor="3M",
            retention_priorities={"incident": 10},
        )
        produced: list[Path] = []

        def produce(folder: Path, measurement: str) -> None:
            produced.append(save(folder, measurement, len(produced), 50 * KB))
            pipeline.submit("records", saved_record(produced[-1], measurement))

        def counts(measurement: str) -> dict[str, Any]:
            return dict(pipeline.status_document()["saved_files"]["measurements"][measurement])

        try:
            produce(elsewhere, "camera")  # the oldest image, on the buffer's disk
            for n in range(25):
                produce(save_dir, "incident" if n % 5 == 4 else "camera")
            assert pipeline.flush_intake(10)
            poll(lambda: counts("camera")["produced"] == 21 and counts("incident")["produced"] == 5, 30, "files noted")
            filler = disk / "other" / "filler.bin"
            filler.parent.mkdir()
            subprocess.run([sys.executable, "-c", f"open({str(filler)!r}, 'wb').write(b'x' * {4608 * KB})"], check=True)

            def free() -> int:
                stats = os.statvfs(disk)
                return stats.f_bavail * stats.f_frsize

            poll(lambda: free() >= 3 * 1024 * 1024 and counts("camera")["evicted"] > 0, 30, "the floor given back")
            gone = [p for p in produced if not p.exists()]
            on_tmpfs = [p for p in produced[1:] if "camera" in p.name]
            assert produced[0].exists() and gone == on_tmpfs[: len(gone)]
            assert counts("incident")["evicted"] == 0 and filler.stat().st_size == 4608 * KB
            for measurement in ("camera", "incident"):  # no destination carries them: the only copies
                c = counts(measurement)
                assert c["produced"] == c["kept"] + c["evicted_unsent"]
            assert counts("camera")["evicted"] == len(gone)
        finally:
            pipeline.stop(0.5)


def test_saved_files_of_an_earlier_run_still_count_after_a_restart(tmp_path: Path) -> None:
    """The account is on disk beside the buffer: files saved before a restart are weighed and evicted after it."""
    settings = DeliveryParams(storage_path=str(tmp_path / "buffer"), flush=0.05, http_server=False, disk_budget="1M")
    produced: list[Path] = []

    def run(count: int) -> dict[str, Any]:
        pipeline = DeliveryPipeline(
            settings,
            {"records": (Collecting(), DestinationDeliveryParams())},
            LOG,
            saved_files_roots=[str(tmp_path / "save")],
        )
        pipeline.start()
        try:
            for _ in range(count):
                produced.append(save(tmp_path / "save", "camera", len(produced), 60 * KB))
                pipeline.submit("records", saved_record(produced[-1], "camera"))
            assert pipeline.flush_intake(10)

            def noted() -> bool:
                return (
                    int(pipeline.status_document()["saved_files"]["bytes"])
                    == sum(p.stat().st_size for p in produced if p.exists())
                    and sum(p.exists() for p in produced) * 60 * KB <= 1024 * 1024
                )

            poll(noted, 30, "the files noted and within the budget")
            return dict(pipeline.status_document()["saved_files"]["measurements"]["camera"])
        finally:
            pipeline.stop(0.5)

    first = run(10)
    assert first["produced"] == 10 and first["evicted"] == 0
    second = run(10)  # 20 x 60 kB: over 1 MB only with the first run's files counted
    assert second["produced"] == 10 and second["evicted"] == 20 - second["kept"] > 0
    assert [p.exists() for p in produced] == [False] * second["evicted"] + [True] * second["kept"]


def test_a_ledger_written_before_files_kept_their_confirmations_is_read_and_upgraded(tmp_path: Path) -> None:
    """A saved_files.sqlite3 of the DC before the `told` column: its files still count, and it is upgraded."""
    import sqlite3

    from dc_destinations.saved_files import SavedFiles

    image = save(tmp_path / "save", "camera", 0, 10 * KB)
    ledger = tmp_path / "saved_files.sqlite3"
    with sqlite3.connect(ledger) as db:
        db.execute(
            "CREATE TABLE files (path TEXT PRIMARY KEY, size INTEGER NOT NULL, measurement TEXT NOT NULL, "
            "run_id TEXT NOT NULL, seq INTEGER NOT NULL, run_index INTEGER NOT NULL, priority INTEGER NOT NULL, "
            "destinations TEXT NOT NULL, owed TEXT NOT NULL, records TEXT NOT NULL)"
        )
        db.execute("INSERT INTO files VALUES (?, ?, 'camera', 'r1', 1, 0, 0, '[]', '[]', '[]')", (str(image), 10 * KB))
    db.close()
    saved = SavedFiles(ledger, {}, RecordingLogger(), roots=[str(tmp_path / "save")])
    saved.open()
    try:
        assert saved.total_bytes == 10 * KB
        assert saved.evict(str(image)) is not None and not image.exists()
        saved.tick()
    finally:
        saved.close()
    with sqlite3.connect(ledger) as db:
        assert db.execute("SELECT count(*) FROM files").fetchone() == (0,)
    db.close()


def test_a_record_naming_a_file_outside_the_save_folders_never_has_it_weighed_or_deleted(tmp_path: Path) -> None:
    """Anything on the ROS graph can publish a record: one naming a file of someone else's (outside the
    save folder and the file destinations' allowed_roots, or reached through a link from inside) is
    left out of the budget, counted as refused, and never deleted however far over budget DC is."""
    settings = DeliveryParams(storage_path=str(tmp_path / "buffer"), flush=0.05, http_server=False, disk_budget="1M")
    victim = save(tmp_path / "elsewhere", "camera", 0, 600 * KB)
    inside = tmp_path / "save"
    inside.mkdir()
    link = inside / "link.jpeg"
    link.symlink_to(victim)
    pipeline = DeliveryPipeline(
        settings, {"records": (Collecting(), DestinationDeliveryParams())}, LOG, saved_files_roots=[str(inside)]
    )
    pipeline.start()
    try:
        pipeline.submit("records", saved_record(victim, "camera"))
        pipeline.submit("records", saved_record(link, "camera"))
        own = [save(inside, "camera", n, 300 * KB) for n in range(1, 6)]  # 1.5 MB of DC's own: over budget
        for path in own:
            pipeline.submit("records", saved_record(path, "camera"))
        assert pipeline.flush_intake(10)
        poll(lambda: not own[0].exists(), 30, "DC's own oldest file evicted")
        document = pipeline.status_document()["saved_files"]
    finally:
        pipeline.stop(0.5)
    assert victim.read_bytes() == bytes([0]) * 600 * KB and link.is_symlink()
    assert document["refused"] == 2
    camera = document["measurements"]["camera"]
    assert camera["produced"] == 5 and camera["evicted"] >= 1


def health_record(n: int) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(rid, "/dc/measurement/health", n, {"n": n, "pad": "x" * 20 * KB, "record_id": rid})


def test_the_budget_holds_after_every_group_commit_not_only_at_the_next_tick(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A clock that stands still: the twice-a-second tick never comes, only admissions keep the budget.
    Images of 100 kB (retention priority 0) and health records of 20 kB (the queue's priority 5) into a
    1 MB budget, a commit at a time: after each, what is on disk of the images plus the records waiting
    is within the budget (the images go, oldest first), and DC's own account says so; then health
    records alone, until every image is gone and the oldest health records go. Every image and record
    is kept or counted evicted."""
    budget = 1024 * KB
    settings = DeliveryParams(
        storage_path=str(tmp_path / "buffer"), flush=0.05, http_server=False, disk_budget="1M", commit_interval=0.0
    )
    held = OnlyWhenParams(conditions=["docked"])
    health = Collecting()
    pipeline = DeliveryPipeline(
        settings,
        {"health": (health, DestinationDeliveryParams(only_when=held, retention_priority=5))},
        LOG,
        clock=lambda: 0.0,
        saved_files_roots=[str(tmp_path / "save")],
    )
    images: list[Path] = []

    def on_disk() -> int:
        waiting = pipeline.metrics()["health"]["buffered_bytes"]
        return int(waiting) + sum(p.stat().st_size for p in images if p.exists())

    pipeline.start()
    try:
        for n in range(40):
            images.append(save(tmp_path / "save", "camera", n, 100 * KB))
            pipeline.submit("health", saved_record(images[-1], "camera"))
            pipeline.submit("health", health_record(n))
            assert pipeline.flush_intake(10)
            assert on_disk() <= budget, f"over the budget after the commit of record {n}"
        camera = pipeline.status_document()["saved_files"]["measurements"]["camera"]
        assert camera["evicted"] > 0 and pipeline.metrics()["health"]["evicted"] == 0
        for n in range(40, 90):
            pipeline.submit("health", health_record(n))
            assert pipeline.flush_intake(10)
            assert on_disk() <= budget, f"over the budget after the commit of record {n}"
        document = pipeline.status_document()
        _print_delivery(document, wide=False)
    finally:
        pipeline.stop(0.5)
    account = document["disk_budget"]
    said = f"disk budget: {account['held']} of {budget} bytes held (records waiting + saved files; at most "
    assert f"{said}{account['most_held']})" in capsys.readouterr().out
    assert account["budget"] == budget and account["most_held"] <= budget and account["checks_left_over"] == 0
    camera = document["saved_files"]["measurements"]["camera"]
    assert camera["produced"] == 40 and camera["evicted"] == 40 and not any(p.exists() for p in images)
    records = document["destinations"]["health"]
    assert records["evicted_by_measurement"]["health"] > 0
    assert records["received"] == records["evicted"] + records["buffered"] == 130 and records["sent"] == 0


def test_a_budget_check_that_keeps_failing_is_counted_and_logged_once_per_burst(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The check after every group commit reads the queues' sizes; here that read fails at every
    check (an I/O error injected at the buffer's boundary: a failing disk cannot be made on demand
    as root). Every record is still committed and delivered, each failed check is counted in the
    metrics and `dc status`, and the log says it once for the burst, not once per commit."""

    def failing(self: SqliteBuffer) -> dict[str, int]:
        raise sqlite3.OperationalError("disk I/O error")

    monkeypatch.setattr(SqliteBuffer, "queued_bytes", failing)
    settings = DeliveryParams(
        storage_path=str(tmp_path / "buffer"), flush=0.05, http_server=False, disk_budget="1M", commit_interval=0.0
    )
    records = Collecting()
    logger = RecordingLogger("tests.test_disk_budget.failing")
    pipeline = DeliveryPipeline(
        settings, {"records": (records, DestinationDeliveryParams())}, logger, clock=lambda: 0.0
    )
    sent = 30
    pipeline.start()
    try:
        for n in range(sent):
            pipeline.submit("records", health_record(n))
            assert pipeline.flush_intake(10)
        # Counted in `sent` once taken off the queue, after send() returned: awaited, or a loaded
        # machine's one batch of 30 is read as sent 0 (a fresh-clone run).
        poll(lambda: pipeline.metrics()["records"]["sent"] == sent, 30, "every record delivered and counted")
        document = pipeline.status_document()
        _print_delivery(document, wide=False)
    finally:
        pipeline.stop(0.5)
    failed = document["disk_budget"]["checks_failed"]
    assert f"{failed} checks FAILED, see the log" in capsys.readouterr().out
    destination = document["destinations"]["records"]
    assert len({r.record_id for r in records.received}) == destination["sent"] == sent
    assert destination["dropped"] == destination["evicted"] == 0
    assert failed >= sent  # one a commit at least, none uncounted
    said = [m for m in logger.at("error") if "keeping the disk budget failed" in m]
    # The first failure, then the burst's summary at the stop (a new burst only after 5 s without a failure,
    # which a very slow machine may give once or twice): not a line per commit.
    assert 1 <= len(said) <= 4, said
    assert "disk I/O error" in said[0]
