"""HTTP destination: one POST per batch to a web endpoint, over a kept-alive connection.

The body is the batch as JSON (an array, lines or a stream of objects) or msgpack, optionally
gzip-compressed. The server's answer decides the outcome: 2xx confirms the batch; 408, 429, 5xx and
network failures are retried (after the server's Retry-After, when it gives one); any other answer
means the server refuses these records, which go to the dead letters. Credentials (basic password,
bearer token, TLS key password) are secrets: never logged, masked should a server echo them.
"""

from __future__ import annotations

import base64
import gzip
import re
import ssl
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qsl

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RejectedError, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import host_param, param, port_problem, url_host
from dc_destinations.http_client import HttpConnection, is_retryable_status, one_line, retry_after_seconds
from dc_destinations.msgpack_format import msgpack_packer
from dc_destinations.probes import connect_probe
from dc_destinations.tls import TlsParams, client_context, is_credential_name, warn_if_credentials_in_clear

FORMATS = ("json", "json_lines", "json_stream", "msgpack")
CONTENT_TYPES = {"json_lines": "application/x-ndjson", "msgpack": "application/msgpack"}
COMPRESSIONS = ("", "gzip")
_HEADER_TOKEN = r"[!#$%&'*+.^_`|~0-9A-Za-z-]+"
_HEADER_COLON = re.compile(rf"^({_HEADER_TOKEN}):[ \t]*(.*)$")
_HEADER_SPACE = re.compile(rf"^({_HEADER_TOKEN})[ \t]+(.*)$")  # Fluent Bit's `Header Name value`
_EXCERPT_CHARS = 200


def _uri_problem(uri: str) -> str | None:
    ok = uri.startswith("/") and uri.isascii() and not any(c.isspace() for c in uri)
    return None if ok else "a path starting with '/', ASCII without spaces (percent-encode the rest)"


def parse_header(text: str) -> tuple[str, str] | None:
    """``"Name: value"`` (or Fluent Bit's ``"Name value"``) as a pair; None when it is neither."""
    match = _HEADER_COLON.match(text.strip()) or _HEADER_SPACE.match(text.strip())
    if match is None or any(c in match.group(2) for c in "\r\n") or not _latin1(match.group(2)):
        return None
    return match.group(1), match.group(2).strip()


def _latin1(text: str) -> bool:
    """HTTP/1.1 header values are bytes; http.client writes them as Latin-1."""
    try:
        text.encode("latin-1")
    except UnicodeEncodeError:
        return False
    return True


@dataclass(frozen=True, kw_only=True, repr=False)
class HttpParams(TlsParams):
    host: str = host_param("the HTTP server")
    port: int = param(80, check=port_problem, doc="TCP port of the HTTP server (443 is usual with `tls`)")
    uri: str = param("/", check=_uri_problem, doc="Path (and query) the batches are POSTed to")
    format: str = param(
        "json",
        choices=FORMATS,
        doc="json: one JSON array; json_lines: one object per line; json_stream: objects back to back; "
        "msgpack: one msgpack array",
    )
    compress: str = param("", choices=COMPRESSIONS, doc="gzip: compress the body (Content-Encoding: gzip); empty: none")
    header: list[str] | str = param(
        [], doc='Extra request headers, "Name: value" each (Fluent Bit\'s "Name value" is accepted too)'
    )
    headers: dict[str, Any] = param(default_factory=dict, doc="Extra request headers as a mapping of name to value")
    header_tag: str = param("", doc="Header that carries the destination's name (Fluent Bit's tag); empty: none")
    allow_duplicated_headers: bool = param(
        True, doc="Send every `header` entry; when false, the last entry of a name replaces the earlier ones"
    )
    http_user: str = param("", doc="User name of HTTP basic authentication; empty: no authentication")
    http_passwd: str = param("", secret=True, doc="Password of HTTP basic authentication (never logged)")
    bearer_token: str = param("", secret=True, doc="Token sent as `Authorization: Bearer <token>` (never logged)")
    timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds to connect and for each read or write")
    retry_after_max: float = param(
        60.0,
        minimum=0,
        maximum=3600,
        doc="Longest Retry-After of a 408, 429 or 5xx answer obeyed, in seconds; 0: ignore it",
    )
    log_response_payload: bool = param(
        True, doc="Quote the start of the server's answer in failure messages and dead letters"
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        for i, entry in enumerate(self.headers_list):
            if parse_header(entry) is None:
                raise ConfigError(f"header[{i}]", f'expected "Name: value", got "{entry}"')
        for name, value in self.headers.items():
            if not re.fullmatch(_HEADER_TOKEN, str(name)):
                raise ConfigError(f"headers.{name}", "expected a header name (letters, digits, '-')")
            if (
                not isinstance(value, (str, int, float, bool))
                or not _latin1(str(value))
                or any(c in str(value) for c in "\r\n")
            ):
                raise ConfigError(f"headers.{name}", "expected a one-line Latin-1 text value")
        if self.bearer_token and self.http_user:
            raise ConfigError("bearer_token", "choose http_user/http_passwd or bearer_token, not both")
        if self.bearer_token and (not _latin1(self.bearer_token) or any(c in self.bearer_token for c in " \r\n")):
            raise ConfigError("bearer_token", "expected a token of Latin-1 characters without spaces")
        if self.http_passwd and not self.http_user:
            raise ConfigError("http_passwd", "set http_user too (basic authentication needs both)")
        if ":" in self.http_user:
            raise ConfigError("http_user", "a user name without ':' (basic authentication separates with it)")
        if self.header_tag and not re.fullmatch(_HEADER_TOKEN, self.header_tag):
            raise ConfigError("header_tag", f'expected a header name, got "{self.header_tag}"')

    @property
    def headers_list(self) -> list[str]:
        return [self.header] if isinstance(self.header, str) else list(self.header)


class Http(Destination[HttpParams]):
    """POST each batch (JSON or msgpack) to an HTTP(S) endpoint; 5xx, 408, 429 and network errors are retried."""

    def __init__(self, context: Any, params: HttpParams) -> None:
        super().__init__(context, params)
        self._headers: list[tuple[str, str]] = []
        self._secrets: list[str] = []
        self._connection: HttpConnection | None = None
        self._tls: ssl.SSLContext | None = None  # for the probe's own connection
        self._encode: Callable[[Sequence[OutgoingRecord]], bytes] = _json_encoder("json")
        self.url = ""

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        scheme = "https" if p.tls_on else "http"
        host = url_host(p.host)
        # Without the query: it may hold an API key, and this URL goes into logs and dead letters.
        self.url = f"{scheme}://{host}:{p.port}{p.uri.split('?', 1)[0]}"
        content_type = CONTENT_TYPES.get(p.format, "application/json")
        headers = [("Content-Type", content_type), ("User-Agent", "dc-destinations")]
        if p.http_user:
            token = base64.b64encode(f"{p.http_user}:{p.http_passwd}".encode()).decode("ascii")
            headers.append(("Authorization", f"Basic {token}"))
            self._secrets = [s for s in (p.http_passwd, token) if s]
        if p.bearer_token:
            headers.append(("Authorization", f"Bearer {p.bearer_token}"))
            self._secrets = [p.bearer_token]
        if p.tls_key_passwd:
            self._secrets.append(p.tls_key_passwd)
        if p.compress:
            headers.append(("Content-Encoding", p.compress))
        if p.header_tag:
            headers.append((p.header_tag, self.context.name))
        for entry in p.headers_list:
            pair = parse_header(entry)
            assert pair is not None  # checked by HttpParams
            headers.append(pair)
        headers.extend((str(name), _header_value(value)) for name, value in p.headers.items())
        self._headers = _merge_headers(headers, keep_duplicates=p.allow_duplicated_headers)
        self._encode = _msgpack_encoder(self._key_path("format")) if p.format == "msgpack" else _json_encoder(p.format)
        tls = self._tls = client_context(p, self._key_path(""), self.context.logger)
        self._connection = self.keep(
            HttpConnection(
                p.host, p.port, timeout=p.timeout, tls=tls, where=self.url, what="cannot POST to", secrets=self._secrets
            )
        )
        self._warn_if_credentials_in_clear()

    def _warn_if_credentials_in_clear(self) -> None:
        p = self.params
        sent = []
        if p.http_user:
            # A user name without a password is still basic authentication, its header readable.
            sent.append(f"the basic authentication of {p.http_user}")
        if p.bearer_token:
            sent.append("the bearer token")
        said = {"authorization"} if sent else set()  # basic auth and the bearer token are that header
        sent.extend(
            f"header {name}" for name, _ in self._headers if is_credential_name(name) and name.lower() not in said
        )
        if any(is_credential_name(key) for key, _ in parse_qsl(p.uri.partition("?")[2], keep_blank_values=True)):
            sent.append("the uri's query parameters")
        fix = "set tls: true (tls_verify: true, tls_ca_file for a private CA)"
        if p.tls_on and not p.tls_verify:
            fix = "set tls_verify: true (tls_ca_file for a private CA)"
        warn_if_credentials_in_clear(
            self.context.logger,
            self.context.name,
            p.host,
            credentials=", ".join(sent),
            verified_tls=p.tls_verified,
            fix=fix,
        )

    def probe(self) -> ProbeResult:
        """Connect (and the TLS handshake) only: no request is sent, for no method is safe on every
        receiver (a HEAD or GET on the uri may have effects on some); credentials are not checked."""
        p = self.params
        server_name = getattr(p, "tls_vhost", "") or p.host
        return connect_probe(p.host, p.port, p.timeout, self._tls, server_name=server_name, what=self.url)

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a server that is down
        # or slow to answer must not hold up activation.
        self.context.logger.info(f"posting {self.params.format} batches to {self.url}")

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        assert self._connection is not None, "send() before on_configure()"
        answer = self._connection.post(self.params.uri, self._headers, self._body(batch))
        status = answer.status
        if 200 <= status < 300:
            return None
        excerpt = one_line(answer.body.decode("utf-8", errors="replace"), _EXCERPT_CHARS)
        if not self.params.log_response_payload:
            excerpt = ""
        # The server's reason first: `dc buffer list` shows the start of the message.
        message = f"HTTP {status} {answer.reason}" + (f": {excerpt}" if excerpt else "")
        message = self._connection.scrub(message + f" ({self.url})")
        if is_retryable_status(status):
            wait = retry_after_seconds(answer.retry_after)
            if wait is None or self.params.retry_after_max <= 0:
                raise RetryableError(message)
            wait = min(wait, self.params.retry_after_max)
            # The sender waits (within its scheduler_cap) before the next attempt, not this thread.
            raise RetryableError(f"{message}; Retry-After {wait:g} s", retry_after=wait)
        if status in (401, 403):
            # The records are refused as before (dead letters, `dc buffer replay` once fixed); the
            # destination is failing at once, for the credentials are wrong for every record.
            raise RejectedError(
                message, fix="check http_user / http_passwd, bearer_token or the header carrying the credentials"
            )
        raise RejectedError(message)

    def _body(self, batch: Sequence[OutgoingRecord]) -> bytes:
        body = self._encode(batch)
        if self.params.compress == "gzip":
            # mtime 0: the same batch compresses to the same bytes on every attempt.
            body = gzip.compress(body, compresslevel=6, mtime=0)
        return body

    def _key_path(self, key: str) -> str:
        return f"destination_server.{self.context.name}" + (f".{key}" if key else "")


def _merge_headers(headers: list[tuple[str, str]], *, keep_duplicates: bool) -> list[tuple[str, str]]:
    """The two defaults first (Content-Type, User-Agent), replaced by configured headers of their name."""
    defaults, configured = headers[:2], headers[2:]
    names = {name.lower() for name, _ in configured}
    merged = [(n, v) for n, v in defaults if n.lower() not in names] + configured
    if keep_duplicates:
        return merged
    last: dict[str, tuple[str, str]] = {}
    for name, value in merged:
        last.pop(name.lower(), None)
        last[name.lower()] = (name, value)
    return list(last.values())


def _json_encoder(fmt: str) -> Callable[[Sequence[OutgoingRecord]], bytes]:
    def encode(batch: Sequence[OutgoingRecord]) -> bytes:
        objects = [record.to_json() for record in batch]
        if fmt == "json_lines":
            text = "".join(o + "\n" for o in objects)
        elif fmt == "json_stream":
            text = "".join(objects)
        else:
            text = "[" + ",".join(objects) + "]"
        return text.encode("utf-8")

    return encode


def _msgpack_encoder(path: str) -> Callable[[Sequence[OutgoingRecord]], bytes]:
    pack = msgpack_packer(path)
    # One msgpack array of the record maps: the same shape as format json, decoded in one call.
    return lambda batch: pack([record.data for record in batch])


def _header_value(value: Any) -> str:
    """A YAML scalar as header text: booleans as YAML writes them, not Python's True."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
