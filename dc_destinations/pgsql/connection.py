"""One kept connection to PostgreSQL, shared by the destinations that write to it (PgSQL, FilesMetrics).

What they have in common: how to connect (libpq options, keepalives so a vanished server is noticed),
how to tell a lost connection from a refused statement, and how to word a failure so that it names
the server and never the password. What they write, and how their table is prepared, stays theirs.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from dc_core.destination import ConfigurationProblem, Destination, ProbeResult, RetryableError
from dc_core.errors import ConfigError
from dc_core.logs import Logger
from dc_core.params import host_param, param, port_problem, url_host
from dc_destinations.tls import warn_if_credentials_in_clear

T = TypeVar("T")

SSLMODES = ("", "disable", "allow", "prefer", "require", "verify-ca", "verify-full")
# PostgreSQL truncates identifiers longer than this (NAMEDATALEN - 1).
MAX_IDENTIFIER = 63
# SQLSTATE classes that mean "this connection is gone": connection exception, and the server
# shutting down (admin_shutdown, crash_shutdown, cannot_connect_now).
_LOST_STATES = ("08", "57P01", "57P02", "57P03")
_AUTH_HINTS = ("password authentication failed", "no password supplied", "authentication failed")
# Failures retrying alone does not mend (dc_destinations.health), by SQLSTATE: invalid authorization
# (28), no such database (3D000), permission refused (42501), no such table or schema (42P01, 3F000).
_SET_UP_STATES = ("28", "3D000", "42501", "42P01", "3F000")
# Whatever the server answers, the message stays readable in `dc buffer list` and logs.
MESSAGE_CHARS = 500


def require_psycopg(name: str, kind: str) -> None:
    """A ConfigError naming the destination ``name`` (of plugin ``kind``) when psycopg is not installed."""
    try:
        import psycopg  # noqa: F401
    except ImportError as exc:
        raise ConfigError(
            f"destination_server.{name}.plugin", f'the {kind} destination needs psycopg (pip install "ros2-dc[pgsql]")'
        ) from exc


def table_problem(table: str) -> str | None:
    parts = table.split(".")
    if not table or len(parts) > 2 or any(not p or len(p.encode()) > MAX_IDENTIFIER or "\0" in p for p in parts):
        return f'a table name or "schema.table", each part 1 to {MAX_IDENTIFIER} bytes'
    return None


def check_server(ssl: bool, sslmode: str, sslrootcert: str) -> None:
    """The checks of a server section that a single parameter cannot make; ConfigError naming the key."""
    if ssl and sslmode in ("disable", "allow", "prefer"):
        raise ConfigError("sslmode", f'"{sslmode}" contradicts ssl: true (use require, verify-ca or verify-full)')
    if sslrootcert and effective_sslmode(ssl, sslmode) not in ("verify-ca", "verify-full", "require"):
        raise ConfigError("sslrootcert", "set sslmode to verify-full (or verify-ca) to use it")


def effective_sslmode(ssl: bool, sslmode: str) -> str:
    """``sslmode`` when given; else ``ssl: true`` is verify-full and no ``ssl`` libpq's prefer.

    ``ssl: true`` used to mean require, which encrypts but accepts any certificate: a man in the
    middle got the password. prefer stays the default without ``ssl``: a local PostgreSQL (the demos',
    a robot's own) rarely has a certificate, and a remote one with a password is warned about
    (:func:`warn_if_password_in_clear`).
    """
    return sslmode or ("verify-full" if ssl else "prefer")


def effective_sslrootcert(ssl: bool, sslmode: str, sslrootcert: str) -> str:
    """``sslrootcert`` when given; for ``ssl: true`` alone, the system's CAs (libpq's ``system``).

    An explicit ``sslmode: verify-full`` without it keeps libpq's own default, ~/.postgresql/root.crt.
    """
    if sslrootcert:
        return sslrootcert
    return "system" if ssl and not sslmode else ""


def verifies_server(sslmode: str, sslrootcert: str) -> bool:
    """Whether a connection with these settings checks who the server is before sending a password.

    verify-full checks the chain and the host name. verify-ca checks the chain only: enough with a
    private CA (``sslrootcert`` that signs only this team's servers), not with the system's CAs,
    which sign certificates for anyone's host names.
    """
    return sslmode == "verify-full" or (sslmode == "verify-ca" and sslrootcert not in ("", "system"))


def warn_if_password_in_clear(logger: Logger, destination: str, settings: ServerSettings, section: str) -> bool:
    """The shared warning (dc_destinations.tls) for a password sent to a remote PostgreSQL unverified.

    ``section`` is the YAML path of the keys (``destination_server.<name>``), for the fix.
    """
    return warn_if_credentials_in_clear(
        logger,
        destination,
        settings.host,
        credentials=f"the password of PostgreSQL user {settings.user or '(default)'} (sslmode {settings.sslmode})"
        if settings.password
        else "",
        verified_tls=verifies_server(settings.sslmode, settings.sslrootcert),
        fix=f"set {section}.ssl: true and no sslmode (verify-full against the system's CAs), "
        f"with {section}.sslrootcert for a private CA",
    )


@dataclass(frozen=True, kw_only=True)
class PostgresServerParams:
    """Where and how a destination logs in to PostgreSQL (PgSQL, FilesMetrics' ``pgsql``), checked together."""

    host: str = host_param("the PostgreSQL server")
    port: int | str = param(5432, check=port_problem, doc='TCP port of the server (the original wrote "5432")')
    user: str = param("", doc="Role to log in as; empty: the system user running DC (libpq's default)")
    password: str = param("", secret=True, doc="Password of `user` (never logged)")
    database: str = param("", doc="Database to connect to; empty: the same name as the user (libpq's default)")
    timestamp_key: str = param(
        "",
        aliases=("timestamp_Key",),
        doc="Record key whose value (epoch seconds or ISO 8601 text) fills the row's time; empty: the record's stamp",
    )
    ssl: bool = param(
        False,
        doc="TLS that checks the server (sslmode verify-full, the system's CAs or sslrootcert); "
        "false: TLS when the server offers it, unchecked (prefer)",
    )
    sslmode: str = param("", choices=SSLMODES, doc="libpq's sslmode, overriding `ssl` (verify-full checks the host)")
    sslrootcert: str = param(
        "",
        doc="CA certificates (PEM) that signed the server's certificate (verify-ca/full); empty with ssl: the system's",
    )
    connect_timeout: int = param(10, minimum=2, maximum=3600, doc="Seconds to connect (and log in)")

    def __post_init__(self) -> None:
        check_server(self.ssl, self.sslmode, self.sslrootcert)

    @property
    def effective_sslmode(self) -> str:
        return effective_sslmode(self.ssl, self.sslmode)

    def server(self) -> ServerSettings:
        return ServerSettings(
            host=self.host,
            port=int(self.port),
            user=self.user,
            password=self.password,
            database=self.database,
            sslmode=self.effective_sslmode,
            sslrootcert=effective_sslrootcert(self.ssl, self.sslmode, self.sslrootcert),
            connect_timeout=self.connect_timeout,
        )


@dataclass(frozen=True, kw_only=True, repr=False)
class ServerSettings:
    """Where and how to log in; empty ``user``/``database`` are libpq's defaults."""

    host: str
    port: int
    user: str
    password: str
    database: str
    sslmode: str
    sslrootcert: str
    connect_timeout: int

    @property
    def address(self) -> str:
        """``postgresql://user@host:port/database``, for messages: no password in it."""
        user = f"{self.user}@" if self.user else ""
        return f"postgresql://{user}{url_host(self.host)}:{self.port}/{self.database}"

    def __repr__(self) -> str:
        return f"ServerSettings({self.address!r}, sslmode={self.sslmode!r})"


class KeptConnection:
    """A connection opened at first use, kept between batches and opened again once it is lost.

    ``prepare(connection)`` runs on every new connection before any work (checking or creating a
    table); a psycopg error there is reported as "cannot prepare <what>", and a RetryableError it
    raises passes as it is. No lock: the destination server never runs ``send`` beside deactivate or
    cleanup (dc_destinations.sender.Gate).
    """

    def __init__(
        self,
        settings: ServerSettings,
        *,
        application_name: str,
        logger: Logger,
        prepare: Callable[[Any], None],
        prepared: str,
    ) -> None:
        self.settings = settings
        self._application_name = application_name[:MAX_IDENTIFIER]
        self._logger = logger
        self._prepare = prepare
        self._prepared = prepared
        self._connection: Any = None  # psycopg.Connection

    @property
    def address(self) -> str:
        return self.settings.address

    def __repr__(self) -> str:
        return f"KeptConnection({self.address!r})"

    def run(self, work: Callable[[Any], T]) -> T:
        """``work(connection)``; a psycopg error it lets through becomes a scrubbed RetryableError."""
        import psycopg

        first = True
        while True:
            reused = self._connection is not None
            try:
                return work(self._connect())
            except psycopg.Error as exc:
                lost = self._lost(exc)
                self._close()  # the next attempt starts afresh, preparation included
                if first and reused and lost:
                    # A kept connection that the server closed while idle (a restart) fails at
                    # its first use: not a failure of this work, so once more on a new one.
                    first = False
                    continue
                message = self.describe(exc)
                fix = self.fix_for(exc)
                if fix:
                    raise ConfigurationProblem(message, fix=fix) from None
                raise RetryableError(message) from None

    def close(self) -> None:
        self._close()

    # -- messages ----------------------------------------------------------------------------------
    def describe(self, exc: BaseException) -> str:
        state = getattr(exc, "sqlstate", None)
        code = f" (SQLSTATE {state})" if state else ""
        return self.scrub(f"PostgreSQL {self.address}: {one_line(str(exc))}{code}")

    def refusal(self, exc: BaseException, what: str = "the record") -> str:
        """The server's reason for refusing a row, as a dead letter says it."""
        diag = getattr(exc, "diag", None)
        primary = getattr(diag, "message_primary", None) or one_line(str(exc))
        detail = getattr(diag, "message_detail", None)
        state = getattr(exc, "sqlstate", None)
        text = f"PostgreSQL refused {what}: {primary}" + (f"; {detail}" if detail else "")
        text += f" (SQLSTATE {state})" if state else ""
        return self.scrub(text[:MESSAGE_CHARS])

    def fix_for(self, exc: BaseException) -> str:
        """What to check when ``exc`` is a failure retrying alone does not mend; "" otherwise.

        A failed connection carries no SQLSTATE (libpq words it): its text is read then.
        """
        state = getattr(exc, "sqlstate", None) or ""
        text = str(exc)
        s = self.settings
        if (
            state.startswith("28")
            or any(h in text for h in _AUTH_HINTS)
            or ("role" in text and "does not exist" in text)
        ):
            return f"check the user ({s.user or 'the system user'}) and the password parameter (or PGPASSWORD)"
        if state == "3D000" or ("database" in text and "does not exist" in text):
            return f"create the database {s.database or s.user or '(the user name)'} or set the database parameter"
        if state == "42501" or "permission denied" in text:
            return f"grant the user {s.user or '(the system user)'} what it needs on {self._prepared}"
        if "certificate verify failed" in text or "does not match host name" in text:
            return "check sslrootcert (the CA that signed the server's certificate) and host"
        if state.startswith(_SET_UP_STATES):
            return f"check {self._prepared} and the database parameter"
        return ""

    def scrub(self, text: str) -> str:
        """The password masked, should a message ever carry it."""
        password = self.settings.password
        return text.replace(password, "***") if password else text

    # -- connection --------------------------------------------------------------------------------
    def _connect(self) -> Any:
        import psycopg

        if self._connection is not None and not self._connection.closed:
            return self._connection
        try:
            connection = psycopg.connect(autocommit=True, **self.connect_options())
        except psycopg.Error as exc:
            detail = one_line(str(exc))
            hint = " (check `user` and `password`)" if any(h in detail for h in _AUTH_HINTS) else ""
            message = self.scrub(f"cannot connect to PostgreSQL {self.address}: {detail}{hint}")
            fix = self.fix_for(exc)
            if fix:
                raise ConfigurationProblem(message, fix=fix) from None
            raise RetryableError(message) from None
        try:
            self._prepare(connection)
        except psycopg.Error as exc:
            connection.close()
            detail = one_line(str(exc))
            message = self.scrub(f"cannot prepare {self._prepared} in {self.address}: {detail}")
            fix = self.fix_for(exc)
            if fix:
                raise ConfigurationProblem(message, fix=fix) from None
            raise RetryableError(message) from None
        except BaseException:
            connection.close()
            raise
        self._connection = connection
        self._logger.info(f"connected to {self.address}")
        return connection

    def connect_options(self) -> dict[str, Any]:
        """libpq's connection parameters (password included: never log them)."""
        s = self.settings
        options: dict[str, Any] = {
            "host": s.host,
            "port": s.port,
            "connect_timeout": s.connect_timeout,
            "sslmode": s.sslmode,
            "application_name": self._application_name,
            # A server that vanished without closing the connection is noticed in about 30 s.
            "keepalives": 1,
            "keepalives_idle": 10,
            "keepalives_interval": 5,
            "keepalives_count": 3,
            "tcp_user_timeout": 30_000,
        }
        for key, value in (("user", s.user), ("password", s.password), ("dbname", s.database)):
            if value:
                options[key] = value
        if s.sslrootcert:
            options["sslrootcert"] = s.sslrootcert
        return options

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


def is_record_error(exc: BaseException) -> bool:
    """Refused because of a row's values: a data exception (22), a constraint (23), a size limit (54)."""
    import psycopg

    state = getattr(exc, "sqlstate", None) or ""
    return isinstance(exc, (psycopg.DataError, psycopg.IntegrityError)) or state.startswith("54")


def one_line(text: str) -> str:
    text = " ".join(text.split())
    return text if len(text) <= MESSAGE_CHARS else text[: MESSAGE_CHARS - 1] + "…"


def keep_database(
    destination: Destination[Any],
    settings: ServerSettings,
    *,
    prepare: Callable[[Any], None],
    prepared: str,
    section: str,
) -> KeptConnection:
    """The PostgreSQL connection of ``destination`` (PgSQL, FilesMetrics), handed to its ``keep``; the
    warning about a password sent in clear said now, at configure, once (``section``: the YAML path of
    the connection's keys)."""
    name, logger = destination.context.name, destination.context.logger
    database = destination.keep(
        KeptConnection(settings, application_name=f"dc {name}", logger=logger, prepare=prepare, prepared=prepared)
    )
    warn_if_password_in_clear(logger, name, settings, section)
    return database


def probe_table(database: KeptConnection, table: Any, name: str) -> ProbeResult:
    """A connection of its own with the real credentials, and the catalog read: does the table
    exist and may this user insert into it (or, if not, create it, as the first batch would).
    ``table`` is its psycopg ``sql.Identifier``; nothing is written (``dc check``)."""
    import psycopg

    try:
        with psycopg.connect(autocommit=True, **database.connect_options()) as connection:
            row = connection.execute(
                """SELECT to_regclass(%(t)s) IS NOT NULL,
                          CASE WHEN to_regclass(%(t)s) IS NULL THEN false
                               ELSE has_table_privilege(to_regclass(%(t)s), 'INSERT') END,
                          has_schema_privilege(current_schema(), 'CREATE'), current_user""",
                {"t": table.as_string(connection)},
            ).fetchone()
    except psycopg.Error as exc:
        return ProbeResult(False, f"cannot connect: {database.describe(exc)}", database.fix_for(exc))
    assert row is not None
    exists, may_insert, may_create, user = row
    where = database.address
    if exists and may_insert:
        return ProbeResult(True, f"connected to {where} as {user}; may insert into table {name}")
    if exists:
        return ProbeResult(
            False, f"{user} may not insert into table {name} ({where})", f"GRANT INSERT ON {name} TO {user}"
        )
    if may_create:
        return ProbeResult(True, f"connected to {where} as {user}; table {name} is created at the first batch")
    return ProbeResult(
        False,
        f"table {name} does not exist in {where} and {user} may not create it",
        f"create the table, or GRANT CREATE ON SCHEMA to {user}",
    )
