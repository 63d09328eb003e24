"""What the destinations that POST over HTTP share: the connection, "not now" answers, Retry-After.

HTTP, InfluxDB and Slack each read a server's answer; the rules for a retry live here once. A
destination passes the wait on as ``RetryableError(message, retry_after=seconds)`` and never waits
itself: the sender's backoff honours it, within ``scheduler_cap`` (dc_destinations.sender).
"""

from __future__ import annotations

import email.utils
import http.client
import ssl
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC

from dc_core.destination import RetryableError
from dc_destinations.connection import Connection, masked

__all__ = ["Answer", "HttpConnection", "masked"]

# Statuses a server uses to say "not now": the same request may succeed later (and any 5xx).
RETRYABLE_STATUSES = frozenset({408, 429})
# Bytes of an answer's body read to keep the connection reusable; a longer body closes it instead.
BODY_READ_LIMIT = 64 * 1024


@dataclass(frozen=True)
class Answer:
    """A server's answer to a POST: its status, reason, (the start of) its body and Retry-After header."""

    status: int
    reason: str
    body: bytes
    retry_after: str | None


class HttpConnection(Connection[http.client.HTTPConnection]):
    """A kept-alive HTTP(S) connection to ``host:port`` (``tls``: dc_destinations.tls.client_context).

    ``what`` starts the text of a network failure ("cannot POST to"), followed by ``where``.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        timeout: float,
        tls: ssl.SSLContext | None,
        where: str,
        what: str,
        secrets: Sequence[str] = (),
    ) -> None:
        super().__init__(
            where, lambda: connection_to(host, port, timeout, tls), _close, timeout=timeout, secrets=secrets
        )
        self.what = what

    def post(self, path: str, headers: Sequence[tuple[str, str]], body: bytes) -> Answer:
        """One POST; a network failure closes the connection and raises a scrubbed RetryableError.

        A kept-alive connection the server closed while idle fails at its first use: not a failure
        of the destination, so the POST is tried once more on a fresh connection.
        """
        reused = self.is_open
        try:
            return self._post(path, headers, body)
        except (OSError, http.client.HTTPException) as first:
            self.close()
            if not (reused and isinstance(first, (http.client.RemoteDisconnected, ConnectionError))):
                raise RetryableError(self.failure(self.what, first)) from None
        try:
            return self._post(path, headers, body)
        except (OSError, http.client.HTTPException) as second:
            self.close()
            raise RetryableError(self.failure(self.what, second)) from None

    def _post(self, path: str, headers: Sequence[tuple[str, str]], body: bytes) -> Answer:
        connection = self.get()
        connection.putrequest("POST", path, skip_accept_encoding=True)
        for name, value in headers:
            connection.putheader(name, value)
        connection.putheader("Content-Length", str(len(body)))
        connection.endheaders(body)
        response = connection.getresponse()
        data = response.read(BODY_READ_LIMIT)
        if not response.isclosed() or response.will_close:
            self.close()  # an endless answer, or the server's wish: drop the connection rather than read on
        return Answer(response.status, response.reason, data, response.getheader("Retry-After"))


def _close(connection: http.client.HTTPConnection) -> None:
    connection.close()


def connection_to(host: str, port: int, timeout: float, tls: ssl.SSLContext | None) -> http.client.HTTPConnection:
    """A connection (not yet opened) to ``host:port``: HTTPS with ``tls`` (dc_destinations.tls.client_context)."""
    if tls is not None:
        return http.client.HTTPSConnection(host, port, timeout=timeout, context=tls)
    return http.client.HTTPConnection(host, port, timeout=timeout)


def is_retryable_status(status: int) -> bool:
    """Whether an answer of ``status`` is worth sending the same request again for."""
    return status in RETRYABLE_STATUSES or status >= 500


def retry_after_seconds(value: str | None, *, now: Callable[[], float] = time.time) -> float | None:
    """A Retry-After header as seconds from now: delay-seconds or an HTTP date (RFC 9110 §10.2.3).

    None when the header is absent or unreadable, for the caller to choose (the backoff alone, or a
    default). A date in the past is 0; a date without a zone is read as GMT, which HTTP dates are.
    """
    if value is None or not value.strip():
        return None
    text = value.strip()
    if text.isdigit():
        return float(text)
    try:
        moment = email.utils.parsedate_to_datetime(text)
    except (TypeError, ValueError):
        return None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return max(0.0, moment.timestamp() - now())


def one_line(text: str, limit: int) -> str:
    """``text`` on one line (runs of white space as one space), cut to ``limit`` characters with "…"."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"
