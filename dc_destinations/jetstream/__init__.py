"""NATS destination: each record published into a JetStream stream, confirmed by the stream's ack.

A fleet's robots hand their records to a replicated stream rather than to the databases: the
stream takes them at the link's pace, and ingest workers (``dc ingest``) write them to the stores
at theirs (docs/fleet.md). A record counts as delivered only once the stream acknowledged storing
it (JetStream's PubAck); until then it stays in DC's buffer, which retries. Every message carries
``Nats-Msg-Id: <record_id>``: a record sent again (a lost ack, a crash between the ack and the
buffer's delete) is stored once within the stream's duplicate window. ``Dc-Topic`` and ``Dc-Stamp``
carry the topic the record came on and its header stamp (ns), which the record's JSON does not
hold: ``dc ingest`` routes by them as destination_server does (dc_destinations.ingest).

nats-py is asyncio: the client lives on an event loop of the destination's own, in a thread under
the server's rule for threads (``context.start_thread``), so that the client answers the server's
pings between batches; ``send`` hands each batch to it and waits. nats-py's own reconnection and
buffering are off: a lost connection is a retryable failure and the next ``send`` connects again,
to the next server of ``servers`` that answers (docs/fleet.md: a cluster).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import threading
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar
from urllib.parse import urlsplit

try:
    import nats.errors
    import nats.js.errors
    from nats.aio.client import Client as NatsClient
    from nats.js import JetStreamContext
    from nats.js.api import StorageType
except ImportError as exc:  # an optional dependency: say which extra brings it
    raise ImportError(f"the NATS destination needs nats-py: pip install 'ros2-dc[nats]' ({exc})") from exc

from dc_core.destination import (
    ConfigurationProblem,
    Destination,
    OutgoingRecord,
    ProbeResult,
    RetryableError,
    SendOutcome,
)
from dc_core.errors import ConfigError, PluginError
from dc_core.params import param
from dc_core.records import MalformedRecord
from dc_destinations.connection import Connection
from dc_destinations.templates import fill_template, template_keys
from dc_destinations.tls import TlsParams, client_context, warn_if_credentials_in_clear

_T = TypeVar("_T")

# Not in a subject published to: the token separator comes from the template only, wildcards and
# white space never (NATS refuses them, or they would change what the subject means).
_SUBJECT_FORBIDDEN = "*> \t\r\n"
HEADER_ID = "Nats-Msg-Id"  # JetStream's deduplication key
HEADER_TOPIC = "Dc-Topic"
HEADER_STAMP = "Dc-Stamp"
_NO_WILDCARDS = "a subject without the wildcards '*' and '>' or white space"
# The server's answer to a connection whose credentials it does not accept.
_AUTH_REFUSALS = ("authorization violation", "authentication", "user authentication expired")
# Seconds a configure-time look at the stream may take: a robot offline at start must not wait long.
_CONFIGURE_CHECK_S = 2.0


def subject_keys(template: str) -> list[str]:
    """The record keys a subject template names; ValueError saying what was expected."""
    keys = template_keys(template, forbidden=_SUBJECT_FORBIDDEN, forbidden_problem=_NO_WILDCARDS)
    literal = template.format_map(dict.fromkeys(keys, "x"))
    if literal.startswith(".") or literal.endswith(".") or ".." in literal:
        raise ValueError("a subject of non-empty tokens separated by '.', like dc.{robot_name}.{name}")
    return keys


def _subject_problem(template: str) -> str | None:
    if not template:
        return "a subject template, like dc.{robot_name}.{name}"
    try:
        subject_keys(template)
    except ValueError as exc:
        return str(exc)
    return None


def _servers_problem(servers: list[str]) -> str | None:
    if not servers:
        return "at least one server URL, like nats://127.0.0.1:4222"
    for url in servers:
        parts = urlsplit(url)
        if parts.scheme not in ("nats", "tls") or not parts.hostname:
            return f"server URLs like nats://host:4222 or tls://host:4222, got {url!r}"
        if parts.username or parts.password:
            return (
                f"no credentials in a server URL ({parts.hostname}): use username/password, token or a credentials file"
            )
        try:
            parts.port  # noqa: B018 (raises on a port out of range)
        except ValueError:
            return f"a port from 1 to 65535 in {url!r}"
    return None


def _stream_problem(name: str) -> str | None:
    ok = name and not any(c in name for c in ".*> \t\r\n/\\")
    return None if ok else "a stream name without '.', '*', '>', '/', '\\' or white space"


@dataclass(frozen=True, kw_only=True, repr=False)
class NatsParams(TlsParams):
    servers: list[str] = param(
        ["nats://127.0.0.1:4222"],
        check=_servers_problem,
        doc="NATS server URLs (nats:// or tls://), tried in turn at each connection: the nodes of a cluster",
    )
    subject: str = param(
        "dc.{robot_name}.{name}",
        check=_subject_problem,
        doc="Subject of each record; {key} is replaced by the record's value of key",
    )
    stream: str = param("DC", check=_stream_problem, doc="JetStream stream the records must be stored in")
    create_stream: bool = param(
        False, doc="Create the stream when missing (false: a missing stream is a configuration error)"
    )
    stream_subjects: list[str] = param(["dc.>"], doc="With create_stream: the subjects the created stream takes")
    stream_replicas: int = param(1, minimum=1, maximum=5, doc="With create_stream: copies kept by a cluster")
    duplicate_window: float = param(
        120.0, minimum=1, doc="With create_stream: seconds within which a record sent again is stored once"
    )
    username: str = param("", doc="User name sent to the server; empty: none")
    password: str = param("", secret=True, doc="Password sent with username (never logged)")
    token: str = param("", secret=True, doc="Authentication token (never logged)")
    nkey_seed_file: str = param("", doc="File holding the NKey seed to sign the server's challenge with")
    credentials_file: str = param("", doc="A .creds file (user JWT and NKey seed) of decentralised authentication")
    tls_hostname: str = param("", doc="Host name the certificate is checked against; empty: the server URL's")
    connect_timeout: float = param(5.0, minimum=0.1, maximum=3600, doc="Seconds to connect to one server")
    publish_timeout: float = param(
        10.0, minimum=0.1, maximum=3600, doc="Seconds to wait for the stream to acknowledge a batch"
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.password and not self.username:
            raise ConfigError("password", "set username too")
        ways = [k for k in ("username", "token", "nkey_seed_file", "credentials_file") if getattr(self, k)]
        if len(ways) > 1:
            raise ConfigError(ways[1], f"one way to authenticate: {ways[0]} is set already")

    @property
    def secrets(self) -> list[str]:
        return [self.password, self.token, self.tls_key_passwd]


class EventLoopThread:
    """An asyncio event loop running in a supervised thread; :meth:`run` waits for a coroutine on it."""

    def __init__(self, start_thread: Callable[[Callable[[], Any], str], threading.Thread], name: str) -> None:
        self._start_thread = start_thread
        self._name = name
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    def run(self, coroutine: Coroutine[Any, Any, _T], timeout: float) -> _T:
        """The coroutine's result; TimeoutError (after cancelling it) when it took longer than ``timeout``."""
        if self._loop is None:
            loop = asyncio.new_event_loop()
            self._thread = self._start_thread(loop.run_forever, self._name)
            self._loop = loop
        future = asyncio.run_coroutine_threadsafe(coroutine, self._loop)
        try:
            return future.result(timeout)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise TimeoutError from None

    def stop(self) -> None:
        loop, self._loop = self._loop, None
        if loop is None:
            return
        # What a connection given up left running (its reader, its subscriptions) ends here, not as
        # "Task was destroyed but it is pending" when the loop is closed.
        with contextlib.suppress(Exception):
            asyncio.run_coroutine_threadsafe(_cancel_others(), loop).result(5.0)
        loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(5.0)
        if not loop.is_running():
            loop.close()


async def _cancel_others() -> None:
    tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


class _Session:
    """One connection to a NATS server and its JetStream context; ``lost`` set once the connection ends."""

    def __init__(self) -> None:
        self.client = NatsClient()
        self.js: JetStreamContext | None = None
        self.lost = asyncio.Event()
        self.errors: list[BaseException] = []

    async def on_error(self, exc: Exception) -> None:
        self.errors.append(exc)  # said in the RetryableError that follows, not logged by nats-py

    async def on_closed(self) -> None:
        self.lost.set()

    @property
    def connected(self) -> bool:
        return bool(self.client.is_connected)


class Nats(Destination[NatsParams]):
    """Publish each record into a NATS JetStream stream; confirmed by the stream's ack, deduplicated by record_id."""

    def __init__(self, context: Any, params: NatsParams) -> None:
        super().__init__(context, params)
        self._keys = subject_keys(params.subject)
        self._loop = EventLoopThread(context.start_thread, f"dc-nats-{context.name}")
        self._session = self.keep(
            Connection("", self._connect, self._close, timeout=params.connect_timeout, usable=lambda s: s.connected)
        )
        self._tls: Any = None
        self.address = ""

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        self.address = self._session.where = ", ".join(p.servers)
        self._session.secrets = p.secrets
        path = f"destination_server.{self.context.name}"
        self._tls = client_context(p, path, self.context.logger)
        for key in ("nkey_seed_file", "credentials_file"):
            file = getattr(p, key)
            if file and not _readable(file):
                raise ConfigError(f"{path}.{key}", f"cannot read {file}")
        credentials = ""
        if p.password:
            credentials = f"the password of {p.username}"
        elif p.token:
            credentials = "the token"
        warn_if_credentials_in_clear(
            self.context.logger,
            self.context.name,
            urlsplit(p.servers[0]).hostname or "",
            credentials=credentials,
            verified_tls=p.tls_verified,
            fix="set tls: true with tls_verify: true (tls_ca_file for a private CA)",
        )
        if not p.create_stream:
            self._check_stream_now()

    def on_deactivate(self) -> None:
        self.close_kept()
        self._loop.stop()

    def on_cleanup(self) -> None:
        self.close_kept()
        self._loop.stop()

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a server that is down
        # must not hold up activation.
        self.context.logger.info(f"publishing to stream {self.params.stream} at {self.address}")

    def probe(self) -> ProbeResult:
        """A connection of its own with the real credentials, and the stream looked up; nothing published."""
        info = asyncio.run(self._look_at_stream(self.params.connect_timeout, create=False))
        p = self.params
        if info is None and p.create_stream:
            return ProbeResult(True, f"connected to {self.address}; stream {p.stream} is created at the first batch")
        if info is None:
            return ProbeResult(
                False,
                f"stream {p.stream} does not exist on {self.address}",
                "create it (nats stream add), or set create_stream: true",
            )
        return ProbeResult(True, f"connected to {self.address}; {info}")

    def _check_stream_now(self) -> None:
        """A missing stream refused at configure, when a server answers quickly; otherwise at the first batch."""
        try:
            info = asyncio.run(self._look_at_stream(min(self.params.connect_timeout, _CONFIGURE_CHECK_S), create=False))
        except RetryableError as exc:
            self.context.logger.info(
                f"stream {self.params.stream} not checked at configure ({exc}): checked at the first batch"
            )
            return
        if info is None:
            raise PluginError(
                f"stream {self.params.stream!r} does not exist on {self.address}: create it (nats stream add), "
                "or set create_stream: true"
            )

    async def _look_at_stream(self, timeout: float, *, create: bool) -> str | None:
        session = await self._open(timeout)
        try:
            return await self._stream(session, create=create)
        finally:
            await session.client.close()

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        outcome = SendOutcome()
        messages: list[tuple[int, str, bytes, dict[str, str]]] = []
        for index, record in enumerate(batch):
            try:
                subject = self.subject_of(record)
                headers = {HEADER_ID: record.record_id, HEADER_TOPIC: record.topic, HEADER_STAMP: str(record.stamp_ns)}
                messages.append((index, subject, record.to_json().encode("utf-8"), headers))
            except (ValueError, MalformedRecord) as exc:
                outcome.reject[index] = str(exc)
        if messages:
            session = self._session.get()
            try:
                self._loop.run(self._publish(session, messages, outcome), self.params.publish_timeout + 5.0)
            except TimeoutError:
                self._session.close()
                raise RetryableError(f"no acknowledgement from {self.address} in time") from None
            retried = [i for i, *_ in messages if i in outcome.retry]
            if retried and len(retried) == len(messages) and not session.connected:
                # The connection went: the whole batch waits, said as the destination's failure.
                self._session.close()
                raise RetryableError(outcome.retry[retried[0]])
        return outcome if outcome.retry or outcome.reject else None

    def subject_of(self, record: OutgoingRecord) -> str:
        """The record's subject; ValueError saying why when the record cannot have one."""
        subject = fill_template(self.params.subject, self._keys, record.data, "subject")
        tokens = subject.split(".")
        if any(not t or any(c in t for c in _SUBJECT_FORBIDDEN) for t in tokens):
            raise ValueError(f"subject {subject!r} has an empty token, a wildcard or white space, which NATS refuses")
        return subject

    async def _publish(
        self, session: _Session, messages: list[tuple[int, str, bytes, dict[str, str]]], outcome: SendOutcome
    ) -> None:
        """Publish every message, then wait for the stream's acks; each record's outcome into ``outcome``."""
        assert session.js is not None
        p = self.params
        acks: dict[int, asyncio.Future[Any]] = {}
        for index, subject, payload, headers in messages:
            try:
                acks[index] = await session.js.publish_async(subject, payload, headers=headers, stream=p.stream)
            except nats.errors.MaxPayloadError:
                outcome.reject[index] = (
                    f"a record of {len(payload)} bytes is over the server's max_payload of "
                    f"{session.client.max_payload} bytes"
                )
            except nats.errors.BadSubjectError:
                outcome.reject[index] = f"NATS refuses the subject {subject!r}"
            except Exception as exc:  # the connection went while publishing: the rest waits
                reason = self._session.failure("cannot publish to", exc)
                for later, *_ in messages:
                    if later not in acks and later not in outcome.reject:
                        outcome.retry[later] = reason
                break
        if not acks:
            return
        lost = asyncio.ensure_future(session.lost.wait())
        try:
            waiting = set(acks.values())
            deadline = asyncio.get_running_loop().time() + p.publish_timeout
            while waiting and not session.lost.is_set():
                left = deadline - asyncio.get_running_loop().time()
                if left <= 0:
                    break
                _done, waiting = await asyncio.wait(waiting | {lost}, timeout=left, return_when=asyncio.FIRST_COMPLETED)
                waiting.discard(lost)
        finally:
            lost.cancel()
        unacknowledged = False
        for index, future in acks.items():
            if not future.done():
                future.cancel()
                unacknowledged = True
                why = "connection lost" if session.lost.is_set() else f"none within {p.publish_timeout:g} s"
                outcome.retry[index] = f"no acknowledgement from stream {p.stream} at {self.address}: {why}"
                continue
            problem = future.exception()
            if problem is None:
                continue
            if isinstance(problem, nats.js.errors.APIError) and problem.code == 400:
                # Refused for this message (the stream's max_msg_size, a subject another stream takes).
                outcome.reject[index] = f"stream {p.stream} refused the record: {problem.description}"
            elif isinstance(problem, nats.js.errors.NoStreamResponseError):
                outcome.retry[index] = (
                    f"no stream answered for this subject at {self.address}: the stream's subjects do not "
                    f"take it, or the stream has no leader"
                )
            else:
                outcome.retry[index] = self._session.scrub(f"stream {p.stream} did not store the record: {problem!r}")
        if unacknowledged:
            # Start afresh: late acks of a connection given up would only be ignored.
            self._session.close()

    # -- connection --------------------------------------------------------------------------------
    def _connect(self) -> _Session:
        p = self.params
        try:
            return self._loop.run(
                self._open_prepared(), 2 * p.connect_timeout * len(p.servers) + p.publish_timeout + 5.0
            )
        except TimeoutError:
            raise RetryableError(f"cannot connect to {self.address}: no answer in time") from None

    async def _open_prepared(self) -> _Session:
        session = await self._open(self.params.connect_timeout)
        try:
            info = await self._stream(session, create=self.params.create_stream)
        except BaseException:
            await session.client.close()
            raise
        if info is None:
            await session.client.close()
            raise ConfigurationProblem(
                f"stream {self.params.stream!r} does not exist on {self.address}",
                fix="create it (nats stream add), or set create_stream: true",
            )
        url = session.client.connected_url
        self.context.logger.info(f"connected to {url.netloc if url else self.address}; {info}")
        return session

    async def _open(self, timeout: float) -> _Session:
        """A connected session to the first server of ``servers`` that accepts one."""
        p = self.params
        session = _Session()
        options: dict[str, Any] = {}
        if p.username:
            options.update(user=p.username, password=p.password or None)
        if p.token:
            options["token"] = p.token
        if p.nkey_seed_file:
            options["nkeys_seed"] = p.nkey_seed_file
        if p.credentials_file:
            options["user_credentials"] = p.credentials_file
        if self._tls is not None:
            options["tls"] = self._tls
            if p.tls_hostname:
                options["tls_hostname"] = p.tls_hostname
        try:
            await session.client.connect(
                servers=p.servers,
                name=f"dc {self.context.name}",
                # DC's buffer retries, with its backoff. nats-py tries each server of the list at least
                # twice before giving up (0 would be for ever), at once rather than after its 2 s wait.
                allow_reconnect=False,
                max_reconnect_attempts=1,
                reconnect_time_wait=0,
                connect_timeout=timeout,  # type: ignore[arg-type]  # a float works: asyncio.wait_for
                error_cb=session.on_error,
                closed_cb=session.on_closed,
                disconnected_cb=session.on_closed,
                **options,
            )
        except Exception as exc:
            await session.client.close()
            last = session.errors[-1] if session.errors else exc
            # The server's refusal may be followed by the reset of the socket it closed: look at every error.
            refusal = next(
                (e for e in (exc, *session.errors) if any(r in str(e).lower() for r in _AUTH_REFUSALS)), None
            )
            if refusal is not None:
                raise ConfigurationProblem(
                    self._session.scrub(f"NATS server {self.address} refused the connection: {refusal}"),
                    fix="check username and password, token, nkey_seed_file or credentials_file",
                ) from None
            raise RetryableError(self._session.failure("cannot connect to", last, timeout=timeout)) from last
        session.js = session.client.jetstream(timeout=p.publish_timeout)
        return session

    async def _stream(self, session: _Session, *, create: bool) -> str | None:
        """What the stream is ("stream DC: subjects dc.>, 3 replicas"); created first when missing and ``create``;
        None when missing."""
        assert session.js is not None
        p = self.params
        try:
            info = await session.js.stream_info(p.stream)
        except nats.js.errors.NotFoundError:
            if not create:
                return None
            info = await session.js.add_stream(
                name=p.stream,
                subjects=p.stream_subjects,
                num_replicas=p.stream_replicas,
                duplicate_window=p.duplicate_window,
                storage=StorageType.FILE,
            )
            self.context.logger.info(f"created stream {p.stream} for {', '.join(p.stream_subjects)}")
        except nats.errors.Error as exc:
            raise RetryableError(self._session.failure(f"cannot look at stream {p.stream} on", exc)) from exc
        config = info.config
        return (
            f"stream {p.stream}: subjects {', '.join(config.subjects or [])}, {config.num_replicas or 1} replica(s), "
            f"duplicate window {config.duplicate_window or 0:g} s"
        )

    def _close(self, session: _Session) -> None:
        self._loop.run(session.client.close(), self.params.connect_timeout)


def _readable(path: str) -> bool:
    try:
        with open(path, "rb"):
            return True
    except OSError:
        return False
