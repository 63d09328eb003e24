"""A throw-away PostgreSQL on loopback, for the PgSQL destination's tests and for trying DC (`dc servers start`).

The cluster lives in its own state folder (``data/``, ``postgres.log``, the unix socket), listens on
127.0.0.1 only and asks for a password (SCRAM) over TCP; the local socket trusts its owner, which is
how the role and database are created. ``fsync`` is off: fast and fine for tests and trials, never
for data that matters (a power cut can corrupt the cluster). PostgreSQL refuses to run as root, so
as root the cluster belongs to the ``postgres`` system user and every command runs through
``runuser``.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dc_bringup.local_servers import ServerError
from dc_bringup.local_servers.processes import alive, kill, log_tail, port_of_last_start, remember_port

INSTALL_HINT = "PostgreSQL is not installed (apt install postgresql)"
_SUPERUSER = "postgres"
_SYSTEM_USER = "postgres"  # the Debian package's account, owner of the cluster when running as root
# A unix socket path longer than this does not fit in sockaddr_un (108 bytes with the terminator).
_MAX_SOCKET_PATH = 107


def find_bin_dir() -> Path | None:
    """The folder of initdb and pg_ctl: on PATH, else Debian's /usr/lib/postgresql/<newest>/bin."""
    on_path = shutil.which("pg_ctl")
    if on_path and shutil.which("initdb"):
        return Path(on_path).parent
    candidates = [Path(p) for p in glob.glob("/usr/lib/postgresql/*/bin") if Path(p, "pg_ctl").is_file()]
    candidates = [p for p in candidates if p.parent.name.isdigit()]
    if not candidates:
        return None
    return max(candidates, key=lambda p: int(p.parent.name))


def missing_reason() -> str | None:
    """Why a PostgresServer cannot run here, or None."""
    if find_bin_dir() is None:
        return INSTALL_HINT
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return 'psycopg is not installed (pip install "ros2-dc[pgsql]")'
    if os.geteuid() == 0:
        try:
            pwd.getpwnam(_SYSTEM_USER)
        except KeyError:
            return f"running as root needs the system user {_SYSTEM_USER!r} (created by apt install postgresql)"
    return None


class PostgresServer:
    """PostgreSQL with one password-protected role and database, on 127.0.0.1."""

    name = "postgres"

    def __init__(
        self,
        state_dir: Path,
        port: int = 0,
        user: str = "dc",
        password: str = "dc",
        database: str = "dc",
    ) -> None:
        self.state_dir = Path(state_dir).absolute()
        self.user = user
        self.password = password
        self.database = database
        self.port = port_of_last_start(self.state_dir, port)
        self._as_root = os.geteuid() == 0

    def __repr__(self) -> str:  # without the password
        return f"PostgresServer({str(self.state_dir)!r}, port={self.port}, user={self.user!r})"

    # -- paths -----------------------------------------------------------------------------------
    @property
    def data_dir(self) -> Path:
        return self.state_dir / "data"

    @property
    def log_file(self) -> Path:
        return self.state_dir / "postgres.log"

    # -- protocol ---------------------------------------------------------------------------------
    def start(self, timeout: float = 30.0) -> None:
        bin_dir = self._bin_dir()
        if self.running():
            self._wait_ready(time.monotonic() + timeout)
            return
        socket_path = self.state_dir / f".s.PGSQL.{self.port}"
        if len(str(socket_path)) > _MAX_SOCKET_PATH:
            raise ServerError(
                f"state folder path too long for PostgreSQL's unix socket ({socket_path}): use a shorter one"
            )
        self._prepare_state_dir()
        if not (self.data_dir / "PG_VERSION").is_file():
            self._initdb(bin_dir)
        self._write_settings()
        remember_port(self.state_dir, self.port)
        deadline = time.monotonic() + timeout
        started = self._run(
            [str(bin_dir / "pg_ctl"), "start", "-w", "-t", str(max(1, int(timeout))), "-D", str(self.data_dir),
             "-l", str(self.log_file)],
            timeout=timeout + 5,
        )  # fmt: skip
        if started.returncode != 0:
            raise ServerError(
                f"PostgreSQL did not start on port {self.port}: {started.stderr.strip()}{self._log_tail()}"
            )
        self._create_role_and_database(deadline)
        self._wait_ready(deadline)

    def stop(self, timeout: float = 10.0) -> None:
        pid = self._pid()
        if pid is None:
            return
        bin_dir = find_bin_dir()
        if bin_dir is not None:
            # fast: roll back open transactions and close the connections, then a clean shutdown.
            with contextlib.suppress(subprocess.TimeoutExpired, OSError):
                self._run(
                    [str(bin_dir / "pg_ctl"), "stop", "-m", "fast", "-w", "-t", str(max(1, int(timeout))),
                     "-D", str(self.data_dir)],
                    timeout=timeout + 2,
                )  # fmt: skip
        # A killed postmaster leaves its pid file; the next start checks that pid and goes on.
        kill(pid)

    def running(self) -> bool:
        return self._pid() is not None

    def settings(self) -> dict[str, str | int]:
        return {
            "host": "127.0.0.1",
            "port": self.port,
            "user": self.user,
            "password": self.password,
            "database": self.database,
        }

    def connect(self) -> Any:
        """A psycopg connection in autocommit, as the server's user to its database (tests, benchmarks)."""
        import psycopg

        return psycopg.connect(
            host="127.0.0.1",
            port=self.port,
            user=self.user,
            password=self.password,
            dbname=self.database,
            autocommit=True,
        )

    def __enter__(self) -> PostgresServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- helpers ----------------------------------------------------------------------------------
    def _bin_dir(self) -> Path:
        reason = missing_reason()
        if reason is not None:
            raise ServerError(reason)
        bin_dir = find_bin_dir()
        assert bin_dir is not None
        return bin_dir

    def _run(self, command: Sequence[str], timeout: float) -> subprocess.CompletedProcess[str]:
        if self._as_root:
            command = ["runuser", "-u", _SYSTEM_USER, "--", *command]
        # cwd: the postgres user may not be allowed into the caller's working folder.
        return subprocess.run(
            list(command), capture_output=True, text=True, timeout=timeout, cwd=self.state_dir, stdin=subprocess.DEVNULL
        )

    def _prepare_state_dir(self) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        if not self._as_root:
            self.state_dir.chmod(0o700)
            return
        account = pwd.getpwnam(_SYSTEM_USER)
        for parent in self.state_dir.parents:
            st = parent.stat()
            if not (st.st_mode & 0o001 or st.st_uid == account.pw_uid):
                raise ServerError(
                    f"the postgres user cannot enter {parent} (mode {st.st_mode & 0o777:o}): "
                    "put the state folder where it can, e.g. under /tmp or /var/lib"
                )
        os.chown(self.state_dir, account.pw_uid, account.pw_gid)
        self.state_dir.chmod(0o700)
        for path in (self.log_file, self.state_dir / "port"):
            if path.exists():
                os.chown(path, account.pw_uid, account.pw_gid)

    def _initdb(self, bin_dir: Path) -> None:
        if self.data_dir.exists() and any(self.data_dir.iterdir()):
            raise ServerError(f"{self.data_dir} is not empty and holds no PostgreSQL cluster: remove it")
        result = self._run(
            [str(bin_dir / "initdb"), "-D", str(self.data_dir), "-U", _SUPERUSER, "-E", "UTF8", "--locale=C",
             "--auth-local=trust", "--auth-host=scram-sha-256", "--no-sync"],
            timeout=120,
        )  # fmt: skip
        if result.returncode != 0:
            raise ServerError(f"initdb failed in {self.data_dir}: {(result.stderr or result.stdout).strip()}")
        with (self.data_dir / "postgresql.conf").open("a") as conf:
            conf.write("\n# Settings of DC's local server (rewritten at each start)\ninclude_if_exists = 'dc.conf'\n")

    def _write_settings(self) -> None:
        # In a file rather than on pg_ctl's command line: pg_ctl passes its -o options through a shell.
        socket_dir = str(self.state_dir).replace("'", "''")
        text = (
            f"port = {self.port}\n"
            "listen_addresses = '127.0.0.1'\n"
            f"unix_socket_directories = '{socket_dir}'\n"
            "unix_socket_permissions = 0700\n"
            "password_encryption = 'scram-sha-256'\n"
            "# For tests and trials only: fast, but a crash of the machine may corrupt the cluster.\n"
            "fsync = off\n"
            "synchronous_commit = off\n"
            "full_page_writes = off\n"
        )
        path = self.data_dir / "dc.conf"
        path.write_text(text)
        if self._as_root:
            account = pwd.getpwnam(_SYSTEM_USER)
            os.chown(path, account.pw_uid, account.pw_gid)

    def _create_role_and_database(self, deadline: float) -> None:
        import psycopg
        from psycopg import sql

        connection = self._superuser_connection(deadline)
        with connection:
            exists = connection.execute("SELECT 1 FROM pg_roles WHERE rolname = %s", (self.user,)).fetchone()
            verb = sql.SQL("ALTER ROLE") if exists else sql.SQL("CREATE ROLE")
            # The password is a literal, not a parameter: utility statements take no parameters.
            connection.execute(
                sql.SQL("{} {} WITH LOGIN PASSWORD {}").format(
                    verb, sql.Identifier(self.user), sql.Literal(self.password)
                )
            )
            if connection.execute("SELECT 1 FROM pg_database WHERE datname = %s", (self.database,)).fetchone() is None:
                try:
                    connection.execute(
                        sql.SQL("CREATE DATABASE {} OWNER {}").format(
                            sql.Identifier(self.database), sql.Identifier(self.user)
                        )
                    )
                except psycopg.Error as exc:
                    raise ServerError(f"cannot create database {self.database!r}: {exc}") from exc

    def _superuser_connection(self, deadline: float) -> Any:
        import psycopg

        while True:
            try:
                return psycopg.connect(
                    host=str(self.state_dir), port=self.port, user=_SUPERUSER, dbname="postgres", autocommit=True
                )
            except psycopg.OperationalError as exc:
                if time.monotonic() > deadline:
                    raise ServerError(
                        f"PostgreSQL on port {self.port} did not answer: {exc}{self._log_tail()}"
                    ) from exc
                time.sleep(0.1)

    def _wait_ready(self, deadline: float) -> None:
        import psycopg

        while True:
            try:
                with psycopg.connect(
                    host="127.0.0.1",
                    port=self.port,
                    user=self.user,
                    password=self.password,
                    dbname=self.database,
                    connect_timeout=2,
                ):
                    return
            except psycopg.OperationalError as exc:
                if time.monotonic() > deadline:
                    detail = str(exc).replace(self.password, "***") if self.password else str(exc)
                    raise ServerError(
                        f"PostgreSQL on port {self.port} did not answer: {detail}{self._log_tail()}"
                    ) from None
                time.sleep(0.1)

    def _pid(self) -> int | None:
        """The postmaster's pid when it runs (from postmaster.pid, checked alive)."""
        try:
            first = (self.data_dir / "postmaster.pid").read_text().split("\n", 1)[0]
            pid = int(first)
        except (OSError, ValueError):
            return None
        return pid if alive(pid) else None

    def _log_tail(self) -> str:
        return log_tail(self.log_file)
