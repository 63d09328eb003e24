"""PgSQL destination: each record a row ``(tag, time, data jsonb, record_id)`` of a PostgreSQL table.

The table is the original's (Fluent Bit's ``pgsql`` output: ``tag``, ``time``, ``data``) plus a
``record_id`` column with a unique index: a batch inserted again after a failure whose outcome was
unknown (the connection died during COMMIT) adds nothing twice (``ON CONFLICT DO NOTHING``), so the
buffer's at-least-once delivery becomes exactly one row per record.

A batch is one transaction of one pipelined multi-row INSERT (psycopg's ``executemany``). When the
server refuses the batch because of its data (a JSON jsonb cannot hold, a value a constraint
forbids), the batch is inserted again row by row, each row in its own savepoint: the refused rows
go to the dead letters with the server's message, the others are committed. Lost or refused
connections, a server shutting down, wrong credentials and anything else are retried: they are
about the server, not the records. The password is never logged nor part of an error message.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import param
from dc_core.records import MalformedRecord

SSLMODES = ("", "disable", "allow", "prefer", "require", "verify-ca", "verify-full")
_EPOCH = dt.datetime(1970, 1, 1)
# PostgreSQL truncates identifiers longer than this (NAMEDATALEN - 1).
_MAX_IDENTIFIER = 63
# SQLSTATE classes that mean "this connection is gone": connection exception, and the server
# shutting down (admin_shutdown, crash_shutdown, cannot_connect_now).
_LOST_STATES = ("08", "57P01", "57P02", "57P03")
_AUTH_HINTS = ("password authentication failed", "no password supplied", "authentication failed")
# Whatever the server answers, the message stays readable in `dc buffer list` and logs.
_MESSAGE_CHARS = 500


def _port_problem(port: int) -> str | None:
    return None if 1 <= port <= 65535 else "a TCP port from 1 to 65535"


def _table_problem(table: str) -> str | None:
    parts = table.split(".")
    if not table or len(parts) > 2 or any(not p or len(p.encode()) > _MAX_IDENTIFIER or "\0" in p for p in parts):
        return f'a table name or "schema.table", each part 1 to {_MAX_IDENTIFIER} bytes'
    return None


@dataclass(frozen=True, kw_only=True, repr=False)
class PgSQLParams:
    host: str = param("127.0.0.1", doc="Host name or IP address of the PostgreSQL server")
    port: int = param(5432, check=_port_problem, doc="TCP port of the PostgreSQL server")
    user: str = param("", doc="Role to log in as; empty: the system user running DC (libpq's default)")
    password: str = param("", secret=True, doc="Password of `user` (never logged)")
    database: str = param("", doc="Database to connect to; empty: the same name as the user (libpq's default)")
    table: str = param("dc", check=_table_problem, doc='Table of the rows ("schema.table" accepted); created if absent')
    timestamp_key: str = param(
        "",
        aliases=("timestamp_Key",),
        doc="Record key whose value (epoch seconds or ISO 8601 text) fills `time`; empty: the record's stamp",
    )
    ssl: bool = param(False, doc="Require TLS (sslmode require); false: TLS when the server offers it (prefer)")
    sslmode: str = param("", choices=SSLMODES, doc="libpq's sslmode, overriding `ssl` (verify-full checks the host)")
    sslrootcert: str = param("", doc="CA certificates (PEM) that signed the server's certificate (verify-ca/full)")
    connect_timeout: int = param(10, minimum=2, maximum=3600, doc="Seconds to connect (and log in)")
    async_: bool = param(False, aliases=("async",), doc="The original's `async`: accepted, no effect")
    min_pool_size: int | str = param("1", doc="Accepted for the original's files; no effect (one connection)")
    max_pool_size: int | str = param("4", doc="Accepted for the original's files; no effect (one connection)")
    cockroachdb: bool = param(False, doc="Accepted for the original's files; no effect")

    def __post_init__(self) -> None:
        if not self.host or any(c.isspace() or c in "/?#" for c in self.host):
            raise ConfigError("host", f'expected a host name or IP address, got "{self.host}"')
        if self.ssl and self.sslmode in ("disable", "allow", "prefer"):
            raise ConfigError(
                "sslmode", f'"{self.sslmode}" contradicts ssl: true (use require, verify-ca or verify-full)'
            )
        if self.sslrootcert and self.effective_sslmode not in ("verify-ca", "verify-full", "require"):
            raise ConfigError("sslrootcert", "set sslmode to verify-full (or verify-ca) to use it")

    @property
    def effective_sslmode(self) -> str:
        return self.sslmode or ("require" if self.ssl else "prefer")

    def __repr__(self) -> str:
        # Written by hand: the generated repr would show `async_`, and the password must stay out.
        shown = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if k != "password")
        return f"PgSQLParams({shown})"


class PgSQL(Destination[PgSQLParams]):
    """Insert each record as a row (tag, time, data jsonb, record_id) of a PostgreSQL table, once."""

    def __init__(self, context: Any, params: PgSQLParams) -> None:
        super().__init__(context, params)
        self._connection: Any = None  # psycopg.Connection, opened with the first batch
        self._lock = threading.Lock()
        self._insert: Any = None
        self.address = ""

    def __repr__(self) -> str:
        return f"PgSQL({self.context.name!r}, {self.address or self.params.host!r})"

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        try:
            from psycopg import sql
        except ImportError as exc:
            raise ConfigError(
                f"destination_server.{self.context.name}.plugin",
                'the PgSQL destination needs psycopg (pip install "ros2-dc[pgsql]")',
            ) from exc
        p = self.params
        host = f"[{p.host}]" if ":" in p.host else p.host
        user = f"{p.user}@" if p.user else ""
        self.address = f"postgresql://{user}{host}:{p.port}/{p.database}"
        self._insert = sql.SQL(
            "INSERT INTO {} (tag, time, data, record_id) VALUES (%s, %s, %s::jsonb, %s)"
            " ON CONFLICT (record_id) DO NOTHING"
        ).format(self._table())

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a database that is down
        # must not hold up activation.
        self.context.logger.info(f"inserting into table {self.params.table} of {self.address}")

    def on_deactivate(self) -> None:
        with self._lock:
            self._close()

    def on_cleanup(self) -> None:
        self.on_deactivate()

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        import psycopg

        tag = self.context.name
        rows: list[tuple[int, tuple[str, dt.datetime, str, str]]] = []
        rejected: dict[int, str] = {}
        for i, record in enumerate(batch):
            try:
                rows.append((i, (tag, self._time(record), record.to_json(), record.record_id)))
            except MalformedRecord as exc:
                rejected[i] = f"not valid JSON: {exc}"
        if rows:
            with self._lock:
                for attempt in (1, 2):
                    reused = self._connection is not None
                    try:
                        rejected.update(self._insert_rows(self._connect(), rows))
                        break
                    except psycopg.Error as exc:
                        lost = self._lost(exc)
                        self._close()  # the next attempt starts afresh, table check included
                        if attempt == 1 and reused and lost:
                            # A kept connection that the server closed while idle (a restart) fails at
                            # its first use: not a failure of this batch, so once more on a new one.
                            continue
                        raise RetryableError(self._describe(exc)) from None
        return SendOutcome(reject=rejected) if rejected else None

    def _insert_rows(
        self, connection: Any, rows: list[tuple[int, tuple[str, dt.datetime, str, str]]]
    ) -> dict[int, str]:
        import psycopg

        try:
            with connection.transaction(), connection.cursor() as cursor:
                cursor.executemany(self._insert, [values for _, values in rows])
            return {}
        except psycopg.Error as exc:
            if not _is_record_error(exc):
                raise
            if len(rows) == 1:
                return {rows[0][0]: self._refusal(exc)}
        # Which rows did the server refuse? Each again in its own savepoint, in one transaction.
        rejected: dict[int, str] = {}
        with connection.transaction():
            for index, values in rows:
                try:
                    with connection.transaction():
                        connection.execute(self._insert, values)
                except psycopg.Error as exc:
                    if not _is_record_error(exc):
                        raise
                    rejected[index] = self._refusal(exc)
        return rejected

    def _time(self, record: OutgoingRecord) -> dt.datetime:
        """The record's time as a naive UTC timestamp (the original's `timestamp` column)."""
        key = self.params.timestamp_key
        if key:
            value = record.data.get(key)
            try:
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    return _EPOCH + dt.timedelta(seconds=float(value))
                if isinstance(value, str):
                    moment = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
                    if moment.tzinfo is not None:
                        moment = moment.astimezone(dt.UTC).replace(tzinfo=None)
                    return moment
            except (ValueError, OverflowError):
                pass  # unreadable: the stamp, rather than refusing a record for its time
        return _EPOCH + dt.timedelta(microseconds=record.stamp_ns // 1000)

    # -- connection --------------------------------------------------------------------------------
    def _connect(self) -> Any:
        import psycopg

        if self._connection is not None and not self._connection.closed:
            return self._connection
        p = self.params
        options: dict[str, Any] = {
            "host": p.host,
            "port": p.port,
            "connect_timeout": p.connect_timeout,
            "sslmode": p.effective_sslmode,
            "application_name": f"dc {self.context.name}"[:_MAX_IDENTIFIER],
            # A server that vanished without closing the connection is noticed in about 30 s.
            "keepalives": 1,
            "keepalives_idle": 10,
            "keepalives_interval": 5,
            "keepalives_count": 3,
            "tcp_user_timeout": 30_000,
        }
        for key, value in (("user", p.user), ("password", p.password), ("dbname", p.database)):
            if value:
                options[key] = value
        if p.sslrootcert:
            options["sslrootcert"] = p.sslrootcert
        try:
            connection = psycopg.connect(autocommit=True, **options)
        except psycopg.Error as exc:
            detail = _one_line(str(exc))
            hint = " (check `user` and `password`)" if any(h in detail for h in _AUTH_HINTS) else ""
            raise RetryableError(self._scrub(f"cannot connect to PostgreSQL {self.address}: {detail}{hint}")) from None
        try:
            self._prepare_table(connection)
        except psycopg.Error as exc:
            connection.close()
            detail = _one_line(str(exc))
            raise RetryableError(self._scrub(f"cannot prepare table {p.table} in {self.address}: {detail}")) from None
        self._connection = connection
        self.context.logger.info(f"connected to {self.address}")
        return connection

    def _prepare_table(self, connection: Any) -> None:
        """The table, its record_id column and their unique index, created when missing.

        Checked in the catalog first: a role allowed to insert into an existing table but not to
        create anything still works.
        """
        from psycopg import sql

        table = self._table()
        name = self.params.table
        found = connection.execute(
            """SELECT to_regclass(%(t)s) IS NOT NULL,
                      EXISTS (SELECT 1 FROM pg_index i JOIN pg_attribute a
                                ON a.attrelid = i.indrelid AND a.attnum = i.indkey[0]
                               WHERE i.indrelid = to_regclass(%(t)s) AND i.indisunique AND i.indnatts = 1
                                 AND a.attname = 'record_id')""",
            {"t": table.as_string(connection)},
        ).fetchone()
        if found is not None and found[1]:
            return
        index = sql.Identifier(f"{name.rsplit('.', 1)[-1]}_record_id"[:_MAX_IDENTIFIER])
        with connection.transaction():
            connection.execute(
                sql.SQL(
                    "CREATE TABLE IF NOT EXISTS {} (tag varchar, time timestamp, data jsonb, record_id text)"
                ).format(table)
            )
            # A table made by the original (or by hand) gets the column and index it lacks.
            connection.execute(sql.SQL("ALTER TABLE {} ADD COLUMN IF NOT EXISTS record_id text").format(table))
            connection.execute(sql.SQL("CREATE UNIQUE INDEX IF NOT EXISTS {} ON {} (record_id)").format(index, table))
        self.context.logger.info(f"table {name} ready in {self.address} (tag, time, data, record_id)")

    def _table(self) -> Any:
        from psycopg import sql

        return sql.Identifier(*self.params.table.split("."))

    def _close(self) -> None:
        if self._connection is not None:
            connection, self._connection = self._connection, None
            # A broken connection may fail to close; it is dropped anyway.
            with contextlib.suppress(Exception):
                connection.close()

    def _lost(self, exc: BaseException) -> bool:
        state = getattr(exc, "sqlstate", None) or ""
        broken = self._connection is None or self._connection.broken or self._connection.closed
        return bool(broken) or state.startswith(_LOST_STATES)

    # -- messages ----------------------------------------------------------------------------------
    def _describe(self, exc: BaseException) -> str:
        state = getattr(exc, "sqlstate", None)
        code = f" (SQLSTATE {state})" if state else ""
        return self._scrub(f"PostgreSQL {self.address}: {_one_line(str(exc))}{code}")

    def _refusal(self, exc: BaseException) -> str:
        diag = getattr(exc, "diag", None)
        primary = getattr(diag, "message_primary", None) or _one_line(str(exc))
        detail = getattr(diag, "message_detail", None)
        state = getattr(exc, "sqlstate", None)
        text = f"PostgreSQL refused the record: {primary}" + (f"; {detail}" if detail else "")
        text += f" (SQLSTATE {state})" if state else ""
        return self._scrub(text[:_MESSAGE_CHARS])

    def _scrub(self, text: str) -> str:
        """The password masked, should a message ever carry it."""
        password = self.params.password
        return text.replace(password, "***") if password else text


def _is_record_error(exc: BaseException) -> bool:
    """Refused because of a row's values: a data exception (22), a constraint (23), a size limit (54)."""
    import psycopg

    state = getattr(exc, "sqlstate", None) or ""
    return isinstance(exc, (psycopg.DataError, psycopg.IntegrityError)) or state.startswith("54")


def _one_line(text: str) -> str:
    text = " ".join(text.split())
    return text if len(text) <= _MESSAGE_CHARS else text[: _MESSAGE_CHARS - 1] + "…"
