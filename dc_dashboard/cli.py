"""``dc dashboard``'s options and what it runs: the web server, or the index and rollup builders."""

from __future__ import annotations

import argparse
import sys

from dc_core.errors import DcError
from dc_dashboard.settings import ParamsMetrics


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default loopback only)")
    p.add_argument("--port", type=int, default=8088, help="port to listen on (default 8088; 0: any free one)")
    p.add_argument(
        "--allowed-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a Host name the dashboard is reached by, besides the --host address and loopback's names "
        "(repeatable); requests naming another host get 421 (DNS-rebinding defence)",
    )
    p.add_argument(
        "--max-connections", type=int, default=16, help="connections served at once; more get 503 (default 16)"
    )
    p.add_argument(
        "--request-timeout",
        type=float,
        default=10.0,
        help="seconds a connection may stay silent while its request is read or answer written (default 10)",
    )
    add_store_arguments(p)
    health = p.add_argument_group("DC's health")
    health.add_argument(
        "--metrics",
        action="append",
        metavar="URL",
        help="a server's metrics, e.g. http://127.0.0.1:2020/api/v1/metrics",
    )
    health.add_argument("--params", help="read the metrics URLs from this parameter file (as dc status --params)")
    p.add_argument(
        "--create-indexes",
        action="store_true",
        help="create the indexes the dashboard needs (CREATE INDEX CONCURRENTLY) and exit",
    )
    p.add_argument(
        "--create-rollups",
        action="store_true",
        help="keep pre-averaged 30 s buckets of the charted measurements (a table and an insert trigger, filled "
        "from the rows there) so the pages of every robot read those, and exit (docs/dashboard.md)",
    )
    p.add_argument("--print-index-sql", action="store_true", help="print those CREATE INDEX statements and exit")


def add_store_arguments(p: argparse.ArgumentParser) -> None:
    """Where DC's PostgreSQL tables and S3 bucket are (dc dashboard, dc reconcile): read by settings.from_sources."""
    pg = p.add_argument_group("PostgreSQL (default: the DC_POSTGRES_* variables of servers.env)")
    pg.add_argument("--pg-host", help="$DC_POSTGRES_HOST, else 127.0.0.1")
    pg.add_argument("--pg-port", type=int, help="$DC_POSTGRES_PORT, else 5432")
    pg.add_argument("--pg-user", help="$DC_POSTGRES_USER")
    pg.add_argument(
        "--pg-password", help="$DC_POSTGRES_PASSWORD (better in the environment: a command line is visible to all)"
    )
    pg.add_argument("--pg-database", help="$DC_POSTGRES_DATABASE")
    pg.add_argument("--table", default="dc", help="the PgSQL destination's table (default dc)")
    pg.add_argument("--files-table", default="files_metrics", help="the FilesMetrics table (default files_metrics)")
    s3 = p.add_argument_group("S3, for the images (default: the DC_S3_* variables of servers.env)")
    s3.add_argument("--s3-endpoint", help="$DC_S3_ENDPOINT; empty: AWS")
    s3.add_argument("--s3-region", help="$DC_S3_REGION, else us-east-1")
    s3.add_argument("--s3-access-key-id", help="$DC_S3_AWS_ACCESS_KEY_ID")
    s3.add_argument("--s3-secret-access-key", help="$DC_S3_AWS_SECRET_ACCESS_KEY (better in the environment)")
    s3.add_argument("--s3-bucket", help="$DC_S3_BUCKET")


def run(args: argparse.Namespace, params_metrics: ParamsMetrics | None = None) -> int:
    """``params_metrics`` reads --params (see dc_dashboard.settings.ParamsMetrics)."""
    try:
        import psycopg  # noqa: F401
    except ImportError:
        print('dc dashboard: psycopg is not installed (pip install "ros2-dc[pgsql,aws]")', file=sys.stderr)
        return 2
    from dc_dashboard import indexes, rollup_setup, server
    from dc_dashboard.settings import from_sources

    try:
        settings = from_sources(args, params_metrics=params_metrics)
    except (DcError, ValueError) as exc:
        print(f"dc dashboard: {exc}", file=sys.stderr)
        return 2
    if args.print_index_sql:
        for statement in indexes.statements(settings.postgres):
            print(statement.as_string(None) + ";")
        return 0
    if args.create_indexes or args.create_rollups:
        done = indexes.create(settings.postgres) if args.create_indexes else 0
        return done or (rollup_setup.create(settings.postgres) if args.create_rollups else 0)
    if args.max_connections < 1 or args.request_timeout <= 0:
        print("dc dashboard: --max-connections must be >= 1 and --request-timeout > 0", file=sys.stderr)
        return 2
    return server.serve(
        settings,
        args.host,
        args.port,
        extra_hosts=args.allowed_host,
        max_connections=args.max_connections,
        timeout=args.request_timeout,
    )
