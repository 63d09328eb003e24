"""`dc check`: the preflight against real servers started here — what a user sees before running DC."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml

from dc_bringup.local_servers.influxdb import InfluxServer
from dc_bringup.local_servers.influxdb import missing_reason as influx_missing
from dc_bringup.local_servers.postgres import missing_reason as postgres_missing
from dc_bringup.local_servers.seaweedfs import SeaweedS3Server
from dc_bringup.local_servers.seaweedfs import missing_reason as s3_missing
from dc_bringup.preflight import FAILED, OK, Row, format_table
from dc_destinations.kinesis.test_kinesis import REGION as KINESIS_REGION
from dc_destinations.kinesis.test_kinesis import Moto
from tests.bringup_util import BIN, REPO
from tests.destination_helpers import running_postgres
from tests.http_receiver import Receiver, free_port
from tests.mqtt_broker import Broker
from tests.mqtt_broker import missing_reason as mqtt_missing

WIDTH = 100


def dc_check(params: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(BIN / "dc"), "check", str(params), *args], capture_output=True, text=True, timeout=90, cwd=cwd
    )


def params_with(tmp_path: Path, destinations: dict[str, dict[str, Any]]) -> Path:
    """Uptime (collected once, judged by a condition) into the given destinations."""
    inputs = {"inputs": ["/dc/measurement/uptime"]}
    document = {
        "measurement_server": {
            "ros__parameters": {
                "measurement_plugins": ["uptime"],
                "condition_plugins": ["booted"],
                "booted": {"plugin": "dc_conditions/IntegerSuperior", "key": "time", "value": 0},
                "uptime": {"plugin": "dc_measurements/Uptime", "if_all_conditions": ["booted"]},
            }
        },
        "destination_server": {
            "ros__parameters": {
                "destination_plugins": list(destinations),
                **{name: {**body, **inputs} for name, body in destinations.items()},
            }
        },
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def row_of(output: str, component: str) -> str:
    """The row of ``component`` with its continuation lines, joined."""
    lines = output.splitlines()
    for i, line in enumerate(lines):
        if line.startswith(component + " "):
            block = [line]
            for more in lines[i + 1 :]:
                if not more.startswith(" "):
                    break
                block.append(more.strip())
            return " ".join(block)
    raise AssertionError(f"no row {component!r} in:\n{output}")


def fits(output: str) -> bool:
    return all(len(line) <= WIDTH for line in output.splitlines())


def test_the_default_job_checks_ok_and_the_table_fits_100_columns(tmp_path: Path) -> None:
    result = dc_check(REPO / "params/default.yaml", cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert fits(out), out
    for component in ("destination stdout", "destination file", "measurement cpu", "measurement network"):
        assert row_of(out, component).split()[2] == OK, out
    assert "0 failed" in out
    assert not (tmp_path / "var/dc/records/system.jsonl").exists(), "without --write-test nothing is written"
    # With --write-test one record goes through each destination's send().
    result = dc_check(REPO / "params/default.yaml", "--write-test", cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "test record dc-check-" in row_of(result.stdout, "destination file write")
    assert '"dc_check"' in (tmp_path / "var/dc/records/system.jsonl").read_text()


def test_an_unreachable_tcp_port_fails_and_the_rest_is_still_checked(tmp_path: Path) -> None:
    port = free_port()  # nothing listens on it
    params = params_with(tmp_path, {"tcp": {"plugin": "dc_destinations/TCP", "host": "127.0.0.1", "port": port}})
    result = dc_check(params, cwd=tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    row = row_of(result.stdout, "destination tcp")
    assert f"destination tcp {FAILED} cannot connect to 127.0.0.1:{port}" in " ".join(row.split()), row
    assert "fix: check that the server runs" in row
    assert row_of(result.stdout, "measurement uptime").split()[2] == OK
    assert "active on this sample" in row_of(result.stdout, "condition booted (uptime)")
    assert fits(result.stdout)


@pytest.mark.skipif(postgres_missing() is not None, reason=str(postgres_missing()))
def test_postgresql_with_a_wrong_password_fails_with_the_fix_and_no_secret(tmp_path: Path) -> None:
    wrong = "not-the-password-4711"
    with running_postgres("dc-check-") as server:
        settings = {
            "plugin": "dc_destinations/PgSQL",
            "host": "127.0.0.1",
            "port": server.port,
            "user": server.user,
            "database": server.database,
            "table": "dc_check",
        }
        params = params_with(tmp_path, {"pg": {**settings, "password": wrong}})
        result = dc_check(params, cwd=tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        row = row_of(result.stdout, "destination pg")
        assert row.split()[2] == FAILED
        assert "password authentication failed" in row
        assert f"fix: check the user ({server.user}) and the password parameter (or PGPASSWORD)" in row
        assert wrong not in result.stdout + result.stderr
        assert fits(result.stdout)

        params = params_with(tmp_path, {"pg": {**settings, "password": server.password}})
        result = dc_check(params, cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert "table dc_check is created at the first batch" in row_of(result.stdout, "destination pg")
        assert server.password not in result.stdout + result.stderr


@pytest.mark.skipif(s3_missing() is not None, reason=str(s3_missing()))
def test_s3_with_a_missing_bucket_fails_with_the_fix(tmp_path: Path) -> None:
    with SeaweedS3Server(tmp_path / "seaweedfs") as server:
        settings = {"plugin": "dc_destinations/S3", **server.settings()}
        params = params_with(tmp_path, {"s3": {**settings, "bucket": "no-such-bucket"}})
        result = dc_check(params, cwd=tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        row = row_of(result.stdout, "destination s3")
        assert row.split()[2] == FAILED
        assert "no bucket no-such-bucket" in row
        assert "fix: create the bucket, or correct bucket / region / endpoint" in row
        assert str(server.settings()["aws_secret_access_key"]) not in result.stdout + result.stderr

        params = params_with(tmp_path, {"s3": settings})
        result = dc_check(params, cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert "exists, credentials accepted" in row_of(result.stdout, "destination s3")


def test_an_invalid_file_is_refused_as_dc_validate_does(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text("measurement_server:\n  ros__parameters:\n    measurement_plugins: [x]\n")
    result = dc_check(params, cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.startswith("invalid: measurement_server.")


def test_the_table_wraps_long_reasons_and_masks_secrets() -> None:
    rows = [Row("destination a-rather-long-destination-name", FAILED, "x " * 80 + "s3cret", fix="do y " * 20)]
    table = format_table(rows, secrets=["s3cret"])
    assert fits(table)
    assert "s3cret" not in table and "***" in table
    assert "fix: do y" in table


# -- the other destinations' probes, each against its server (or the stand-in the plugin's tests use) --
@pytest.mark.skipif(mqtt_missing() is not None, reason=str(mqtt_missing()))
def test_mqtt_with_a_wrong_password_fails_and_the_right_one_connects(tmp_path: Path) -> None:
    with Broker(tmp_path / "broker", users={"robot": "right-password-1"}) as broker:
        settings = {"plugin": "dc_destinations/MQTT", "port": broker.port, "username": "robot", "topic": "dc"}
        result = dc_check(params_with(tmp_path, {"mq": {**settings, "password": "wrong-password-2"}}), cwd=tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        row = row_of(result.stdout, "destination mq")
        assert row.split()[2] == FAILED and "fix: check username and password" in row, row
        assert "wrong-password-2" not in result.stdout
        result = dc_check(params_with(tmp_path, {"mq": {**settings, "password": "right-password-1"}}), cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert "connected to mqtt://127.0.0.1" in row_of(result.stdout, "destination mq")


@pytest.mark.skipif(influx_missing() is not None, reason=str(influx_missing()))
def test_influxdb_with_a_missing_database_fails_with_the_fix(tmp_path: Path) -> None:
    with InfluxServer(tmp_path / "influx", database="dc", user="admin", password="influx-pass-3") as server:
        settings = {"plugin": "dc_destinations/InfluxDB", **server.settings()}
        result = dc_check(params_with(tmp_path, {"influx": {**settings, "database": "elsewhere"}}), cwd=tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        row = row_of(result.stdout, "destination influx")
        assert "no database 'elsewhere'" in row and "fix: CREATE DATABASE elsewhere" in row, row
        result = dc_check(params_with(tmp_path, {"influx": {**settings, "http_passwd": "wrong"}}), cwd=tmp_path)
        assert "fix: check http_user and http_passwd" in row_of(result.stdout, "destination influx")
        result = dc_check(params_with(tmp_path, {"influx": settings}), cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert "influx-pass-3" not in result.stdout


def test_http_and_slack_probes_connect_and_send_nothing(tmp_path: Path) -> None:
    with Receiver() as receiver:
        port = receiver.port
        destinations: dict[str, dict[str, Any]] = {
            "web": {"plugin": "dc_destinations/HTTP", "host": "127.0.0.1", "port": port, "uri": "/in"},
            # Slack cannot be reached from here: its probe is a connection to the webhook's host, the
            # same here with a webhook on loopback (the plugin's own tests use such a stand-in too).
            "chat": {"plugin": "dc_destinations/Slack", "webhook": f"http://127.0.0.1:{port}/services/T0/B0/tok3n"},
        }
        result = dc_check(params_with(tmp_path, destinations), cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert f"connected to http://127.0.0.1:{port}/in" in row_of(result.stdout, "destination web")
        assert "connected to" in row_of(result.stdout, "destination chat")
        assert "tok3n" not in result.stdout
        assert receiver.requests == [], "a probe posts nothing"


def test_kinesis_probe_against_moto_finds_a_missing_stream(tmp_path: Path) -> None:
    # Kinesis cannot be reached from here: moto_server stands in for it, as in the plugin's own tests.
    moto = Moto().start()
    try:
        settings: dict[str, Any] = {
            "plugin": "dc_destinations/KinesisStreams",
            "stream": "robots",
            "region": KINESIS_REGION,
            "endpoint": moto.url,
            "aws_access_key_id": "AKIAIOSFODNN7EXAMPLE",
            "aws_secret_access_key": "kinesis-secret-5",
        }
        result = dc_check(params_with(tmp_path, {"stream": settings}), cwd=tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        assert "fix: create the stream, or correct stream / region" in row_of(result.stdout, "destination stream")
        moto.create_stream("robots")
        result = dc_check(params_with(tmp_path, {"stream": settings}), cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert "is ACTIVE" in row_of(result.stdout, "destination stream")
        assert "kinesis-secret-5" not in result.stdout
    finally:
        moto.stop()


def test_a_sample_failing_its_schema_fails_only_when_it_would_be_dropped(tmp_path: Path) -> None:
    schema = tmp_path / "uptime.json"
    schema.write_text('{"type": "object", "properties": {"time": {"type": "integer", "maximum": 0}}}')
    params = params_with(tmp_path, {"out": {"plugin": "dc_destinations/Null"}})
    document = yaml.safe_load(params.read_text())
    uptime = document["measurement_server"]["ros__parameters"]["uptime"]
    uptime.update(json_schema_path=str(schema), enable_validator=True, drop_invalid=True)
    params.write_text(yaml.safe_dump(document))
    result = dc_check(params, cwd=tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "sample fails its schema, dropped: time:" in row_of(result.stdout, "measurement uptime")
    uptime["drop_invalid"] = False
    params.write_text(yaml.safe_dump(document))
    result = dc_check(params, cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert row_of(result.stdout, "measurement uptime").split()[2] == "warn"


@pytest.mark.skipif(postgres_missing() is not None or s3_missing() is not None, reason="no PostgreSQL or SeaweedFS")
def test_files_metrics_probes_its_database_and_every_storage_bucket(tmp_path: Path) -> None:
    with running_postgres("dc-check-fm-") as pg, SeaweedS3Server(tmp_path / "seaweedfs") as s3:
        store = s3.settings()
        minio = {
            "endpoint": f"127.0.0.1:{s3.port}",
            "use_ssl": False,
            "access_key_id": store["aws_access_key_id"],
            "secret_access_key": store["aws_secret_access_key"],
            "bucket": "no-such-bucket",
            "src_fields": ["local_paths.png"],
            "upload_fields": ["remote_paths.minio.png"],
        }
        pgsql = {"host": "127.0.0.1", "port": pg.port, "user": pg.user, "password": pg.password}
        body = {
            "plugin": "dc_destinations/FilesMetrics",
            "file_storage": ["minio"],
            "minio": minio,
            "pgsql": {**pgsql, "database": pg.database},
        }
        result = dc_check(params_with(tmp_path, {"fm": body}), cwd=tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        row = row_of(result.stdout, "destination fm")
        assert "no minio: bucket no-such-bucket" in row and "fix: create the bucket" in row, row
        body["minio"] = {**minio, "bucket": store["bucket"]}
        result = dc_check(params_with(tmp_path, {"fm": body}), cwd=tmp_path)
        assert result.returncode == 0, result.stdout + result.stderr
        assert "table files_metrics is created at the first batch" in row_of(result.stdout, "destination fm")
        assert pg.password not in result.stdout
