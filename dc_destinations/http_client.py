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
from collections.abc import Callable, Iterable
from datetime import UTC

# Statuses a server uses to say "not now": the same request may succeed later (and any 5xx).
RETRYABLE_STATUSES = frozenset({408, 429})


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


def masked(text: str, secrets: Iterable[str]) -> str:
    """``text`` with every one of ``secrets`` replaced by ``***``, should a server echo a credential back.

    Longest first, so that a secret holding another (a URL and its token) is masked whole.
    """
    for secret in sorted(secrets, key=len, reverse=True):
        if secret:
            text = text.replace(secret, "***")
    return text
