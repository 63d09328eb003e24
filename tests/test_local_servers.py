"""`dc servers run`: the local PostgreSQL, S3 and InfluxDB come up, say where they are, and go away on Ctrl-C."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import stat
import subprocess
import time
from pathlib import Path

import psycopg
import pytest
import yaml

from dc_bringup.local_servers.run import DEFAULT_PORTS
from tests.bringup_util import BIN

pytestmark = pytest.mark.e2e


def test_servers_run_until_interrupted_with_their_settings_kept_private(tmp_path: Path) -> None:
    state = Path(os.environ.get("TMPDIR", "/tmp")) / f"dc-servers-{os.getpid()}"  # postgres must enter it
    # PostgreSQL's usual port held (by this test, or by a `dc demo` of another test): a free one is taken.
    holder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    with contextlib.suppress(OSError):
        holder.bind(("127.0.0.1", DEFAULT_PORTS["postgres"]))
    run = subprocess.Popen(
        [str(BIN / "dc"), "servers", "run", "postgres", "influxdb", "--state-dir", str(state)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    settings_file = state / "settings.yaml"
    try:
        deadline = time.monotonic() + 90
        while not settings_file.exists() and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)  # polling a file another process writes: no event to wait on
        assert settings_file.exists(), run.stdout.read() if run.stdout else ""
        assert stat.S_IMODE(settings_file.stat().st_mode) == 0o600  # it holds passwords
        settings = yaml.safe_load(settings_file.read_text())
        pg = settings["postgres"]
        with psycopg.connect(
            host=pg["host"], port=pg["port"], user=pg["user"], password=pg["password"], dbname=pg["database"]
        ) as connection:
            assert connection.execute("select 1").fetchone() == (1,)
        assert settings["influxdb"]["port"] > 0
        # servers.env: the same settings as DC_<SERVER>_<KEY> for the demos' ${...} references.
        env_file = state / "servers.env"
        assert stat.S_IMODE(env_file.stat().st_mode) == 0o600
        sourced = subprocess.run(
            ["bash", "-c", f". {env_file} && echo $DC_POSTGRES_PORT && echo $DC_POSTGRES_PASSWORD"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        assert sourced.stdout.split() == [str(pg["port"]), pg["password"]]
        assert pg["port"] != DEFAULT_PORTS["postgres"]
    finally:
        run.send_signal(signal.SIGINT)
        output, _ = run.communicate(timeout=60)
        holder.close()
    assert run.returncode == 0, output
    assert f"postgres: port {DEFAULT_PORTS['postgres']} is taken, using a free one" in output
    assert "postgres: stopped" in output and "influxdb: stopped" in output
    assert pg["password"] not in output  # the settings file has it, the terminal does not
    subprocess.run(["rm", "-rf", str(state)], check=False)


def test_the_s3_server_starts_on_other_ports_when_one_of_its_own_was_taken_meanwhile(tmp_path: Path) -> None:
    # free_port() and weed's bind are apart: a process (another test's server, say) may take a port
    # between them. The S3 port is the caller's; the internal ones are chosen again.
    from dc_bringup.local_servers.seaweedfs import SeaweedS3Server

    state = tmp_path / "s3"
    state.mkdir()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        admin = taken.getsockname()[1]
        (state / "ports.json").write_text(json.dumps({"admin": admin}))
        server = SeaweedS3Server(state)
        try:
            server.start()
            client = server.client()
            client.put_object(Bucket=server.bucket, Key="k", Body=b"v")
            assert client.get_object(Bucket=server.bucket, Key="k")["Body"].read() == b"v"
        finally:
            server.stop()
    assert "Port allocation failed" in server.log_file.read_text()
    assert json.loads((state / "ports.json").read_text())["admin"] != admin
