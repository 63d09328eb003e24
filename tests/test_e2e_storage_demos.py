"""The storage demos (params/demos/tb3_*.yaml) run as docs/demos.md says: `dc sim`, the local servers'
settings in the environment (what `. var/dc/servers/servers.env` gives), dc-bringup with sim time; then
what a backend engineer would query is there."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers import postgres, seaweedfs
from dc_bringup.local_servers.run import environment
from tests.bringup_util import BIN, REPO, Bringup
from tests.destination_helpers import running_postgres

pytestmark = pytest.mark.e2e

DEMOS = REPO / "params" / "demos"


@dataclass
class StorageServers:
    """PostgreSQL and S3 as `dc servers run` starts them, their settings in the environment."""

    pg: postgres.PostgresServer
    s3: seaweedfs.SeaweedS3Server

    def query(self, sql: str) -> list[tuple[Any, ...]]:
        import psycopg

        dsn = (
            f"host=127.0.0.1 port={self.pg.port} user={self.pg.user} password={self.pg.password} "
            f"dbname={self.pg.database}"
        )
        try:
            with psycopg.connect(dsn) as connection:
                return connection.execute(sql).fetchall()
        except psycopg.errors.UndefinedTable:
            return []  # DC creates its tables with its first batch


@pytest.fixture
def storage_servers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[StorageServers]:
    for missing in (postgres.missing_reason(), seaweedfs.missing_reason()):
        if missing is not None:
            pytest.skip(missing)
    with running_postgres("dc-pg-demo-") as pg:
        servers = StorageServers(pg, seaweedfs.SeaweedS3Server(tmp_path / "s3"))
        try:
            servers.s3.start()
            for name, value in environment({"postgres": pg.settings(), "s3": servers.s3.settings()}).items():
                monkeypatch.setenv(name, value)
            yield servers
        finally:
            servers.s3.stop()


@pytest.fixture
def simulated_robot() -> Iterator[Any]:
    """Starts `dc sim --clock` in a run's environment; stopped at the end of the test."""
    started: list[subprocess.Popen[bytes]] = []

    def start(run: Bringup) -> None:
        command = [str(BIN / "dc"), "sim", "--clock", "--rate", "4", "--duration", "120"]
        started.append(subprocess.Popen(command, env=run.env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))

    yield start
    for sim in started:
        sim.terminate()
        sim.wait(10)


def test_the_influxdb_demo_writes_robot_and_system_points(
    tmp_path: Path, simulated_robot: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dc_bringup.local_servers.influxdb import InfluxServer, missing_reason

    if missing_reason() is not None:
        pytest.skip(str(missing_reason()))
    with InfluxServer(tmp_path / "influxdb", database="dc") as influx:
        for name, value in environment({"influxdb": influx.settings()}).items():
            monkeypatch.setenv(name, value)
        with Bringup(DEMOS / "tb3_influxdb.yaml", tmp_path / "home", args=["--use-sim-time"]) as run:
            run.wait_ready()
            simulated_robot(run)

            def points(measurement: str) -> list[dict[str, Any]]:
                (result,) = influx.query(f'SELECT * FROM "{measurement}"', database="dc")
                series = result.get("series", [])
                assert isinstance(series, list)
                return [dict(zip(s["columns"], v, strict=True)) for s in series for v in s["values"]]

            run.wait_until(lambda: len(points("dc_distance_traveled")) >= 3, 90, "3 distance_traveled points")
            run.wait_until(lambda: bool(points("dc_position") and points("dc_cpu")), 60, "position and cpu points")
        distance = points("dc_distance_traveled")
        position = points("dc_position")[-1]
    # Nested and flattened as in the original; the fields named as Telegraf's, dotted; tags kept.
    assert distance[-1]["distance_traveled.distance_traveled"] > 0
    assert {"position.x", "position.y", "position.yaw"} <= set(position)
    assert position["robot_name"] == "C3PO" and position["run_id"]


def test_the_postgresql_and_minio_demo_stores_rows_files_and_their_status(
    tmp_path: Path, simulated_robot: Any, storage_servers: StorageServers
) -> None:
    query, s3 = storage_servers.query, storage_servers.s3
    with Bringup(DEMOS / "tb3_pgsql_minio.yaml", tmp_path / "home", args=["--use-sim-time"]) as run:
        run.wait_ready()
        simulated_robot(run)
        wanted = {"robot", "system", "map", "distance_traveled", "front_camera"}

        def names() -> set[str]:
            return {row[0] for row in query("select distinct data->>'name' from dc")}

        run.wait_until(lambda: wanted <= names(), 120, f"rows of {sorted(wanted)} in table dc")
        run.wait_until(
            lambda: bool(query("select 1 from files_metrics where deleted and local_path like '%.jpg'")),
            60,
            "an inspected image uploaded, verified and deleted",
        )
    files = query(
        "select local_path, remote_path, uploaded, deleted, on_filesystem, size, group_name, robot_name "
        "from files_metrics"
    )
    objects = s3.objects()
    done = [f for f in files if f[3]]
    assert done, files
    for local_path, remote_path, uploaded, _deleted, on_filesystem, size, group_name, robot_name in done:
        # Deleted only once verified in the bucket, and the bucket has those bytes.
        assert uploaded and not on_filesystem and not (tmp_path / "home" / local_path).exists()
        key = remote_path.removeprefix(f"s3://{s3.bucket}/")
        assert len(objects[key]) == size
        assert key.startswith("C3PO/2023/11/14/") and group_name in ("map", "front_camera")
        assert robot_name == "C3PO"
    assert any(k.endswith(".png") for k in objects) and any(k.endswith(".jpg") for k in objects)


def test_the_qr_codes_demo_keeps_codes_in_postgresql_and_inspected_images_in_the_bucket(
    tmp_path: Path, simulated_robot: Any, storage_servers: StorageServers
) -> None:
    query, s3 = storage_servers.query, storage_servers.s3
    with Bringup(DEMOS / "tb3_qrcodes_minio_pgsql.yaml", tmp_path / "home", args=["--use-sim-time"]) as run:
        run.wait_ready()
        simulated_robot(run)

        def verified_images() -> list[tuple[Any, ...]]:
            return query(
                "select local_path, remote_path, uploaded, deleted, on_filesystem, size, robot_name from files_metrics "
                "where group_name = 'front_camera' and deleted"
            )

        # The first shelf's stop, at the simulator's 4x: its record, and its image verified and deleted.
        run.wait_until(lambda: bool(verified_images()), 90, "an inspected image uploaded, verified and deleted")
        run.wait_until(lambda: bool(query("select 1 from dc where data->>'name' = 'robot'")), 30, "a robot row")
    codes = [
        row[0] for row in query("select data->'inspected'->'barcode' from dc where data->>'name' = 'front_camera'")
    ]
    images = verified_images()
    objects = s3.objects()
    # A record per stop, with the codes read there; the shelf labels' QR codes among them.
    assert codes and all(read for read in codes), codes
    assert any(code["type"] == "QRCODE" and code["data"] for read in codes for code in read), codes
    for local_path, remote_path, uploaded, _deleted, on_filesystem, size, robot_name in images:
        key = remote_path.removeprefix(f"s3://{s3.bucket}/")
        assert key.startswith("C3PO/") and key.endswith(".jpg"), key
        assert uploaded and not on_filesystem and not (tmp_path / "home" / local_path).exists()
        assert len(objects[key]) == size and robot_name == "C3PO"
