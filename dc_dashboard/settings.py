"""Where the dashboard reads from: PostgreSQL, S3 and the metrics URLs, from arguments or DC_* variables.

The variables are those ``dc servers run`` writes to servers.env (DC_POSTGRES_*, DC_S3_*), so a shell
that ran the demos runs the dashboard too. Passwords and keys stay in this object: its repr leaves
them out, and nothing prints or logs it whole.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class PostgresSettings:
    host: str = "127.0.0.1"
    port: int = 5432
    user: str = ""
    password: str = field(default="", repr=False)
    database: str = ""
    table: str = "dc"
    files_table: str = "files_metrics"
    connect_timeout: int = 5
    # A page never waits longer than this on one statement: a query the indexes do not serve fails
    # with a message instead of holding a browser and a server thread.
    statement_timeout_ms: int = 15000

    def connect_kwargs(self) -> dict[str, Any]:
        kwargs: dict[str, Any] = {
            "host": self.host,
            "port": self.port,
            "connect_timeout": self.connect_timeout,
            # UTC session: the filters' dates are UTC and so is what a timestamptz column gives back,
            # whatever zone the server or the database was set to. No JIT: the pages' queries are index
            # seeks and ranges, and a plan's estimated cost (a branch never run counts too) made PostgreSQL
            # compile one for 3.4 s of its 3.42 s (the Files page of a run, 30 day partitions). 16 MB to
            # hash in (with the default 4 MB, a fleet's hour of positions, 360,000 rows, was sorted on disk
            # to be bucketed: 0.7 s of the query's 1.5 s; its hash takes 8 MB); at most 16 connections.
            # Parallel workers read the rows of a plot when they are many (a fleet's hour: 360,000 positions,
            # 72,000 cpu records): at the default costs (0.1 a row sent to the leader, 1000 to start) PostgreSQL
            # priced that above reading them alone; a robot's hour stays serial.
            "options": (
                f"-c statement_timeout={self.statement_timeout_ms} -c TimeZone=UTC -c jit=off -c work_mem=16MB"
                " -c parallel_tuple_cost=0.01 -c parallel_setup_cost=100"
            ),
            "application_name": "dc-dashboard",
        }
        for key in ("user", "password", "database"):
            if getattr(self, key):
                kwargs["dbname" if key == "database" else key] = getattr(self, key)
        return kwargs

    def address(self) -> str:
        """For messages: no password."""
        return f"postgresql://{self.user + '@' if self.user else ''}{self.host}:{self.port}/{self.database}"


@dataclass(frozen=True)
class S3Settings:
    endpoint: str = ""
    region: str = "us-east-1"
    access_key_id: str = ""
    secret_access_key: str = field(default="", repr=False)
    bucket: str = ""

    @property
    def configured(self) -> bool:
        return bool(self.bucket)


@dataclass(frozen=True)
class DashboardSettings:
    postgres: PostgresSettings
    s3: S3Settings
    # Each a destination (or group, measurement) server's GET /api/v1/metrics, named for the page.
    metrics: tuple[tuple[str, str], ...] = ()


# A parameter file's path -> (label, URL) of each metrics server it enables. The command that starts the
# dashboard gives it (dc_bringup knows the servers' configurations; the dashboard, below it, does not).
ParamsMetrics = Callable[[str], list[tuple[str, str]]]


def from_sources(
    args: Any, environ: Mapping[str, str] | None = None, params_metrics: ParamsMetrics | None = None
) -> DashboardSettings:
    """Arguments first, then the DC_POSTGRES_* / DC_S3_* variables, then the defaults."""
    env = os.environ if environ is None else environ

    def pick(arg: str, variable: str, default: str = "") -> str:
        value = getattr(args, arg, None)
        return str(value) if value not in (None, "") else env.get(variable, default)

    postgres = PostgresSettings(
        host=pick("pg_host", "DC_POSTGRES_HOST", "127.0.0.1"),
        port=int(pick("pg_port", "DC_POSTGRES_PORT", "5432")),
        user=pick("pg_user", "DC_POSTGRES_USER"),
        password=pick("pg_password", "DC_POSTGRES_PASSWORD"),
        database=pick("pg_database", "DC_POSTGRES_DATABASE"),
        table=getattr(args, "table", None) or "dc",
        files_table=getattr(args, "files_table", None) or "files_metrics",
    )
    s3 = S3Settings(
        endpoint=pick("s3_endpoint", "DC_S3_ENDPOINT"),
        region=pick("s3_region", "DC_S3_REGION", "us-east-1"),
        access_key_id=pick("s3_access_key_id", "DC_S3_AWS_ACCESS_KEY_ID"),
        secret_access_key=pick("s3_secret_access_key", "DC_S3_AWS_SECRET_ACCESS_KEY"),
        bucket=pick("s3_bucket", "DC_S3_BUCKET"),
    )
    return DashboardSettings(postgres, s3, tuple(metrics_urls(args, params_metrics)))


def metrics_urls(args: Any, params_metrics: ParamsMetrics | None = None) -> list[tuple[str, str]]:
    """(label, URL) of every --metrics URL and of each server whose HTTP server --params enables."""
    urls = [(url, url) for url in getattr(args, "metrics", None) or []]
    params = getattr(args, "params", None)
    if params:
        if params_metrics is None:
            raise ValueError("--params: no reader of parameter files was given (start the dashboard by dc dashboard)")
        urls.extend(params_metrics(params))
    return urls
