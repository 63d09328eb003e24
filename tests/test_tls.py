"""Credentials never leave for another host unverified without a warning; PostgreSQL's ``ssl: true`` verifies.

Configuration only for the warnings: 192.0.2.1 is TEST-NET-1 (RFC 5737), and configuring a
destination sends nothing, so no test here ever connects to it. The PostgreSQL test at the end
runs a real server on loopback with TLS on and a certificate made by the test.
"""

from __future__ import annotations

import os
import pwd
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.postgres import missing_reason
from dc_core.destination import Destination, RetryableError
from dc_core.errors import ConfigError
from dc_core.params import parse_params
from dc_core.plugins import load_plugin
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.tls import TlsParams, client_context, is_credential_name, is_loopback
from tests.destination_helpers import UPTIMES, running_postgres

REMOTE = "192.0.2.1"  # TEST-NET-1: documentation only, never routed


def configured(kind: str, **params: Any) -> tuple[Destination[Any], RecordingLogger]:
    """The destination of plugin ``kind`` configured with ``params``: its configure warnings."""
    cls: Any = load_plugin("destinations", kind)
    context = FakeContext(name="sink")
    plugin = cls(context, parse_params(cls.Params, params, "destination_server.sink"))
    plugin.on_configure()
    return plugin, context.logger


def warnings_of(kind: str, **params: Any) -> list[str]:
    plugin, logger = configured(kind, **params)
    plugin.on_cleanup()
    return [line for line in logger.at("warning") if "without verified TLS" in line]


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.8.9.10", True),
        ("::1", True),
        ("[::1]", True),
        ("::ffff:127.0.0.1", True),
        ("localhost", True),
        ("LOCALHOST.", True),
        ("db.localhost", True),
        ("192.0.2.1", False),
        ("10.0.0.1", False),
        ("robot.local", False),
        ("localhost.example.com", False),
        ("", False),
    ],
)
def test_loopback_is_judged_by_the_address_without_asking_dns(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_credential_headers_are_recognised() -> None:
    assert all(map(is_credential_name, ["Authorization", "X-Api-Key", "X-Auth-Token", "api_key", "Cookie"]))
    assert not any(map(is_credential_name, ["Content-Type", "X-Robot", "db", "precision"]))


# (plugin, parameters sending a credential to REMOTE in clear, the same verified, a word of the warning)
CASES: list[tuple[str, dict[str, Any], dict[str, Any] | None, str]] = [
    ("dc_destinations/PgSQL", {"user": "dc", "password": "s3cret"}, {"ssl": True}, "PostgreSQL user dc"),
    (
        "dc_destinations/PgSQL",
        {"user": "dc", "password": "s3cret", "sslmode": "require"},
        {"sslmode": "verify-full"},
        "sslmode require",
    ),
    (
        "dc_destinations/PgSQL",
        {"user": "dc", "password": "s3cret", "sslmode": "verify-ca", "sslrootcert": "system"},
        {"sslmode": "verify-ca", "sslrootcert": "/etc/dc/team-ca.pem"},
        "sslmode verify-ca",
    ),
    ("dc_destinations/HTTP", {"http_user": "dc", "http_passwd": "s3cret"}, {"tls": True}, "basic authentication"),
    ("dc_destinations/HTTP", {"bearer_token": "t0ken"}, {"tls": True}, "bearer token"),
    ("dc_destinations/HTTP", {"header": ["X-Api-Key: k3y"]}, {"tls": True}, "header X-Api-Key"),
    ("dc_destinations/HTTP", {"headers": {"Authorization": "Basic eA=="}}, {"tls": True}, "header Authorization"),
    ("dc_destinations/HTTP", {"uri": "/in?api_key=k3y"}, {"tls": True}, "query parameters"),
    ("dc_destinations/HTTP", {"bearer_token": "t0ken", "tls": True, "tls_verify": False}, None, "tls_verify: true"),
    ("dc_destinations/MQTT", {"username": "dc", "password": "s3cret"}, {"tls": True}, "password of dc"),
    ("dc_destinations/MQTT", {"username": "dc", "password": "s3cret", "tls": True, "tls_verify": False}, None, "dc"),
    ("dc_destinations/InfluxDB", {"http_token": "t0ken", "bucket": "b", "org": "o"}, {"tls": True}, "the token"),
    ("dc_destinations/InfluxDB", {"http_user": "dc", "http_passwd": "s3cret"}, {"tls": True}, "password of dc"),
    ("dc_destinations/InfluxDB", {"http_token": "t0ken", "bucket": "b", "tls": True, "tls_verify": False}, None, "tok"),
]


@pytest.mark.parametrize(("kind", "clear", "verified", "word"), CASES)
def test_credentials_to_a_remote_host_in_clear_are_warned_about_once(
    kind: str, clear: dict[str, Any], verified: dict[str, Any] | None, word: str
) -> None:
    (line,) = warnings_of(kind, host=REMOTE, **clear)
    assert "destination sink" in line and REMOTE in line and word in line
    for secret in ("s3cret", "t0ken", "k3y"):
        assert secret not in line
    # Loopback: nobody else on the path.
    assert warnings_of(kind, host="127.0.0.1", **clear) == []
    assert warnings_of(kind, host="localhost", **clear) == []
    if verified is not None:
        assert warnings_of(kind, host=REMOTE, **{**clear, **verified}) == []


@pytest.mark.parametrize(
    ("kind", "params"),
    [
        ("dc_destinations/PgSQL", {}),  # no password: nothing of DC's to read (the data is another matter)
        ("dc_destinations/HTTP", {"header": ["X-Robot: r2"]}),
        ("dc_destinations/MQTT", {"username": "dc"}),
        ("dc_destinations/InfluxDB", {}),
        ("dc_destinations/TCP", {}),
    ],
)
def test_no_credentials_no_warning(kind: str, params: dict[str, Any]) -> None:
    assert warnings_of(kind, host=REMOTE, **params) == []


# -- one TLS parameter set: the flat tls_* keys, and TCP's original tls: section as their alias -----------


@pytest.mark.parametrize("kind", ["dc_destinations/HTTP", "dc_destinations/MQTT", "dc_destinations/InfluxDB"])
def test_the_tls_section_is_an_alias_of_the_flat_keys_on_every_destination(kind: str) -> None:
    section = {"active": True, "verify": "off", "ca_file": "", "key_passwd": ""}
    plugin, logger = configured(kind, tls=section)
    params: Any = plugin.params
    assert (params.tls, params.tls_verify, params.tls_ca_file) == (True, False, "")
    (note,) = logger.at("warning")
    assert "destination_server.sink.tls: the tls: section" in note and "deprecated" in note
    flat, flat_logger = configured(kind, tls=True, tls_verify=False)
    assert flat_logger.at("warning") == [], "the flat spelling is not deprecated"
    assert flat.params == params, "the same settings either way"


def test_the_two_spellings_do_not_mix_and_errors_name_the_key_as_written(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"^x\.tls_verify: write the TLS settings either as tls_\* keys"):
        parse_params(TlsParams, {"tls": {"active": True}, "tls_verify": False}, "x")
    with pytest.raises(ConfigError, match=r"^x\.tls\.key_file: set crt_file too"):
        parse_params(TlsParams, {"tls": {"active": True, "key_file": "k.pem"}}, "x")
    with pytest.raises(ConfigError, match=r"^x\.tls\.vhost: this destination has no vhost setting"):
        parse_params(TlsParams, {"tls": {"active": True, "vhost": "example.org"}}, "x")
    missing = str(tmp_path / "none.pem")
    for spelled, params in (
        ("tls_ca_file", {"tls": True, "tls_ca_file": missing}),
        ("tls.ca_file", {"tls": {"active": True, "ca_file": missing}}),
    ):
        with pytest.raises(
            ConfigError, match=rf"^destination_server\.d\.{re.escape(spelled)}: cannot load .*: no such file"
        ):
            client_context(parse_params(TlsParams, params, "x"), "destination_server.d")
    off = parse_params(TlsParams, {"tls_ca_file": missing}, "x")
    assert client_context(off, "destination_server.d") is None, "files are read only when tls is on"


def test_object_stores_over_plain_http_are_warned_about() -> None:
    keys = {"access_key_id": "AKIAEXAMPLE", "secret_access_key": "s3cretkey", "bucket": "dc-bucket",
            "src_fields": ["local_paths.pgm"], "upload_fields": ["remote_paths.minio.pgm"]}  # fmt: skip
    (line,) = warnings_of("dc_destinations/MinIO", endpoint=f"{REMOTE}:9000", use_ssl=False, **keys)
    assert "access key AKIAEXAMPLE" in line and "s3cretkey" not in line and "https" in line
    assert warnings_of("dc_destinations/MinIO", endpoint=f"{REMOTE}:9000", use_ssl=True, **keys) == []
    assert warnings_of("dc_destinations/MinIO", endpoint="127.0.0.1:9000", use_ssl=False, **keys) == []
    aws = {"aws_access_key_id": "AKIAEXAMPLE", "aws_secret_access_key": "s3cretkey", "region": "eu-west-1"}
    (line,) = warnings_of("dc_destinations/S3", bucket="dc-bucket", endpoint=f"http://{REMOTE}:9000", **aws)
    assert "AKIAEXAMPLE" in line and "s3cretkey" not in line
    assert warnings_of("dc_destinations/S3", bucket="dc-bucket", endpoint=REMOTE, **aws) == []  # a host: https
    (line,) = warnings_of("dc_destinations/KinesisStreams", stream="s", endpoint=f"http://{REMOTE}:4567", **aws)
    assert REMOTE in line
    assert warnings_of("dc_destinations/KinesisStreams", stream="s", endpoint="http://127.0.0.1:4567", **aws) == []


def test_a_slack_webhook_over_plain_http_is_warned_about() -> None:
    (line,) = warnings_of("dc_destinations/Slack", webhook=f"http://{REMOTE}/services/T000/B000/XXXXXXXXXXXX")
    assert "webhook URL" in line and "XXXXXXXXXXXX" not in line
    assert warnings_of("dc_destinations/Slack", webhook="https://hooks.slack.com/services/T000/B000/XXXXXXXX") == []


def test_files_metrics_warns_for_its_database_and_its_store() -> None:
    lines = warnings_of(
        "dc_destinations/FilesMetrics",
        file_storage=["minio"],
        minio={"endpoint": f"{REMOTE}:9000", "use_ssl": False, "src_fields": ["local_paths.pgm"],
               "upload_fields": ["remote_paths.minio.pgm"]},
        pgsql={"host": REMOTE, "user": "dc", "password": "s3cret"},
    )  # fmt: skip
    assert len(lines) == 2
    assert any("PostgreSQL user dc" in line and "pgsql.ssl: true" in line for line in lines)
    assert any("sink.minio" in line for line in lines)


# -- PostgreSQL: ssl: true is verify-full -----------------------------------------------------------------


def test_pgsql_ssl_true_asks_libpq_to_verify_the_host_against_the_systems_cas() -> None:
    pytest.importorskip("psycopg")
    plugin, _ = configured("dc_destinations/PgSQL", host="db.example.org", ssl=True, password="s3cret")
    options = plugin._database.connect_options()  # type: ignore[attr-defined]
    assert (options["sslmode"], options["sslrootcert"]) == ("verify-full", "system")
    plugin, _ = configured("dc_destinations/PgSQL", ssl=True, sslrootcert="/etc/dc/ca.pem")
    options = plugin._database.connect_options()  # type: ignore[attr-defined]
    assert (options["sslmode"], options["sslrootcert"]) == ("verify-full", "/etc/dc/ca.pem")
    # An explicit sslmode is kept as written, libpq's own default CA file included.
    plugin, _ = configured("dc_destinations/PgSQL", ssl=True, sslmode="require")
    options = plugin._database.connect_options()  # type: ignore[attr-defined]
    assert options["sslmode"] == "require" and "sslrootcert" not in options
    plugin, _ = configured("dc_destinations/PgSQL")
    assert plugin._database.connect_options()["sslmode"] == "prefer"  # type: ignore[attr-defined]


def _certificate(folder: Path) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and its key, readable by the server's user only."""
    crt, key = folder / "server.crt", folder / "server.key"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj", "/CN=127.0.0.1",
         "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost", "-keyout", str(key), "-out", str(crt)],
        check=True,
        capture_output=True,
    )  # fmt: skip
    key.chmod(0o600)
    if os.geteuid() == 0:  # PostgreSQL runs as postgres then, and refuses a key it does not own
        account = pwd.getpwnam("postgres")
        for path in (crt, key):
            os.chown(path, account.pw_uid, account.pw_gid)
    return crt, key


@pytest.mark.skipif(missing_reason() is not None or shutil.which("openssl") is None, reason="PostgreSQL or openssl")
def test_pgsql_ssl_true_connects_with_the_right_ca_and_refuses_an_unknown_certificate(tmp_path: Path) -> None:
    psycopg = pytest.importorskip("psycopg")
    from psycopg import sql

    with running_postgres("dc-tls-") as server:
        crt, key = _certificate(server.state_dir)
        with psycopg.connect(host=str(server.state_dir), port=server.port, user="postgres", autocommit=True) as su:
            for setting, path in (("ssl_cert_file", crt), ("ssl_key_file", key)):
                su.execute(sql.SQL("ALTER SYSTEM SET {} = {}").format(sql.Identifier(setting), sql.Literal(str(path))))
            su.execute("ALTER SYSTEM SET ssl = on")
            su.execute("SELECT pg_reload_conf()")
            # The reload is asynchronous: wait until a new backend sees TLS on.
            for _ in range(100):
                with psycopg.connect(host=str(server.state_dir), port=server.port, user="postgres") as check:
                    if check.execute("SHOW ssl").fetchone()[0] == "on":
                        break
            else:
                pytest.fail("PostgreSQL did not turn TLS on")
        common = {"host": "127.0.0.1", "port": server.port, "user": server.user, "password": server.password,
                  "database": server.database, "table": "tls_rows", "ssl": True}  # fmt: skip

        # The server's own CA given: verified, and the rows arrive.
        plugin, logger = configured("dc_destinations/PgSQL", **common, sslrootcert=str(crt))
        try:
            assert plugin.send(UPTIMES) is None
        finally:
            plugin.on_cleanup()
        assert not [line for line in logger.at("warning") if "TLS" in line]
        dsn = {k: common[k] for k in ("host", "port", "user", "password")} | {"dbname": server.database}
        with psycopg.connect(**dsn, sslmode="require") as check:
            assert check.execute("SELECT count(*) FROM tls_rows").fetchone()[0] == len(UPTIMES)
            assert check.execute("SELECT ssl FROM pg_stat_ssl WHERE pid = pg_backend_pid()").fetchone()[0]

        # The system's CAs do not know this certificate: refused, saying why, the password not sent.
        plugin, _ = configured("dc_destinations/PgSQL", **common)
        try:
            with pytest.raises(RetryableError) as refused:
                plugin.send(UPTIMES)
        finally:
            plugin.on_cleanup()
        assert "certificate verify failed" in str(refused.value)
        assert server.password not in str(refused.value)
