"""Slack destination: records posted as messages to a Slack incoming webhook, at most one message a second.

A message carries up to ``max_records_per_message`` records, one line each from ``template``.
Slack allows an incoming webhook about one message per second and answers ``429`` with
``Retry-After`` beyond that. This destination keeps to ``rate`` itself, waiting inside ``send``
(which runs on the destination's own thread) for at most a few seconds, then hands what is left back
to the buffer. A ``429`` hands the rest back at once with Slack's ``Retry-After`` as the
``retry_after`` of the retry: the sender's backoff waits it out, not this thread.

The webhook URL is a credential (whoever has it can post to the channel): it never appears in a
log, an error, ``last_error``, a dead letter or a repr; messages show ``https://hooks.slack.com/***``.
"""

from __future__ import annotations

import http.client
import json
import ssl
import string
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RejectedError, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import param
from dc_core.records import measurement_of
from dc_destinations.http_client import is_retryable_status, masked, one_line, retry_after_seconds
from dc_destinations.probes import connect_probe
from dc_destinations.tls import url_host, url_is_verified_tls, warn_if_credentials_in_clear

# Longest wait inside one send(): longer would hold up the destination's stop and hide progress.
SEND_BUDGET_S = 5.0
# Slack cuts a message at 40,000 characters; a line longer than this is cut with "…".
LINE_CHARS = 3000
RETRY_AFTER_DEFAULT_S = 1.0
RETRY_AFTER_MAX_S = 3600.0
_BODY_READ_LIMIT = 64 * 1024
_EXCERPT_CHARS = 200


def _webhook_problem(url: str) -> str | None:
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname or any(c.isspace() for c in url):
        return "an https:// URL of a Slack incoming webhook"
    return None


def _template_problem(template: str) -> str | None:
    try:
        list(string.Formatter().parse(template))
    except ValueError as exc:
        return f"a template with balanced braces ({exc}; write {{{{ and }}}} for literal braces)"
    return None


@dataclass(frozen=True, kw_only=True)
class SlackParams:
    webhook: str = param(secret=True, doc="Slack incoming-webhook URL (a credential: never logged)")
    template: str = param(
        "", check=_template_problem, doc='Text of a record, e.g. "{name}: {cpu.average:.1f} %"; empty: a summary'
    )
    max_records_per_message: int = param(10, minimum=1, maximum=100, doc="Records per message, one line each")
    rate: float = param(1.0, minimum=0.01, maximum=100, doc="Most messages per second (Slack allows 1)")
    timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds to connect and for each read or write")

    def __post_init__(self) -> None:
        # Checked here rather than with `check=`: its message would quote the value, the secret.
        expected = _webhook_problem(self.webhook)
        if expected is not None:
            raise ConfigError("webhook", f"expected {expected} (the value is not shown: it is a secret)")


class _Missing:
    """A template field the record lacks: left in the text as written, so the message shows what is missing."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __format__(self, spec: str) -> str:
        return "{" + self.name + (f":{spec}" if spec else "") + "}"

    def __str__(self) -> str:
        return "{" + self.name + "}"

    __repr__ = __str__


class _RecordFormatter(string.Formatter):
    """``str.format`` over a flat mapping: ``{cpu.average}`` is the key "cpu.average", not an attribute."""

    def get_field(self, field_name: str, args: Sequence[Any], kwargs: Mapping[str, Any]) -> tuple[Any, str]:
        return kwargs.get(field_name, _Missing(field_name)), field_name

    def format_field(self, value: Any, format_spec: str) -> str:
        if isinstance(value, _Missing):
            return format(value, format_spec)
        if not format_spec and (value is None or isinstance(value, (bool, dict, list))):
            return escape(json.dumps(value, ensure_ascii=False, separators=(",", ":")))
        return escape(super().format_field(value, format_spec))


def escape(text: str) -> str:
    """Slack's three control characters: a record value must not become a link or an @channel."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def flatten(data: Mapping[str, Any]) -> dict[str, Any]:
    """Every key of the record, nested ones by dotted path too: ``{"cpu": {"average": 3}}`` gives
    "cpu" and "cpu.average"; list items are "list.0", "list.1"..."""
    out: dict[str, Any] = {}

    def walk(prefix: str, value: Any) -> None:
        out[prefix] = value
        children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
        for key, child in children:
            walk(f"{prefix}.{key}", child)

    for key, value in data.items():
        walk(str(key), value)
    return out


def _stamp(stamp_ns: int) -> str:
    return datetime.fromtimestamp(stamp_ns / 1e9, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def summary(record: OutgoingRecord) -> str:
    """The default text: "`cpu` at 2025-03-01T11:08:26Z: {...the record...}"."""
    name = record.data.get("name") or measurement_of(record.topic) or record.topic
    return f"`{escape(str(name))}` at {_stamp(record.stamp_ns)}: {escape(record.to_json())}"


def _shorten(line: str) -> str:
    return line if len(line) <= LINE_CHARS else line[: LINE_CHARS - 1] + "…"


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    """urllib would turn a redirected POST into a GET without the message: a redirect is an answer instead."""

    def redirect_request(self, *args: Any, **kwargs: Any) -> None:
        return None


class Slack(Destination[SlackParams]):
    """Post records as messages to a Slack incoming webhook, at most one message a second."""

    def __init__(self, context: Any, params: SlackParams) -> None:
        super().__init__(context, params)
        self._formatter = _RecordFormatter()
        self._opener = urllib.request.build_opener(_NoRedirect())
        self._secrets: list[str] = []
        self._next_post_at = 0.0  # monotonic: the rate's next free slot
        self._template_failing = False
        self.url = ""

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        parts = urllib.parse.urlsplit(self.params.webhook)
        self.url = f"{parts.scheme}://{parts.netloc.rpartition('@')[2]}/***"
        # The path (T…/B…/token) and query are the credential; its long pieces are masked too,
        # should a proxy or a server quote part of the request back.
        secret = self.params.webhook.split(parts.netloc, 1)[1]
        pieces = [p for p in secret.replace("?", "/").replace("&", "/").split("/") if len(p) >= 8]
        self._secrets = sorted({self.params.webhook, secret, *pieces} - {"", "/"}, key=len, reverse=True)
        warn_if_credentials_in_clear(  # Slack's own webhooks are https; a relay of one may not be
            self.context.logger,
            self.context.name,
            url_host(self.params.webhook),
            credentials="the webhook URL",
            verified_tls=url_is_verified_tls(self.params.webhook),
            fix="use an https:// webhook URL",
        )

    def probe(self) -> ProbeResult:
        """A connection (and TLS handshake) to the webhook's host only: a webhook has no read-only
        request, and any POST to it posts a message in the channel. The webhook itself is unchecked."""
        parts = urllib.parse.urlsplit(self.params.webhook)
        host = parts.hostname or ""
        tls = ssl.create_default_context() if parts.scheme == "https" else None
        port = parts.port or (443 if tls is not None else 80)
        result = connect_probe(host, port, self.params.timeout, tls, what=self.url)
        if result.ok:
            return ProbeResult(True, result.reason + " (the webhook itself is checked by --write-test only)")
        return result

    def on_activate(self) -> None:
        self.context.logger.info(f"posting records to the Slack webhook {self.url}")

    # -- sending -----------------------------------------------------------------------------------
    def text(self, record: OutgoingRecord) -> str:
        """The line of one record: ``template`` over its keys, or the summary."""
        if not self.params.template:
            return _shorten(summary(record))
        fields = {
            "json": record.to_json(),
            "data": record.to_json(),
            "topic": record.topic,
            "stamp": _stamp(record.stamp_ns),
            "record_id": record.record_id,
        }
        fields.update(flatten(record.data))  # a key of the record wins over the extras of the same name
        try:
            line = self._formatter.vformat(self.params.template, (), fields)
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            # "{name:.1f}" on a string, say: the record still goes out, as the summary.
            if not self._template_failing:
                self.context.logger.warning(
                    f"template does not fit a record of {record.topic} ({exc}); sending the summary instead"
                )
            self._template_failing = True
            return _shorten(summary(record))
        return _shorten(line)

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        deadline = time.monotonic() + SEND_BUDGET_S
        size = self.params.max_records_per_message
        chunks = [range(start, min(start + size, len(batch))) for start in range(0, len(batch), size)]
        retry: dict[int, str] = {}
        reject: dict[int, str] = {}
        retry_after: float | None = None
        posted = 0
        for n, chunk in enumerate(chunks):
            rest = [i for c in chunks[n:] for i in c]
            wait_reason = self._wait_for_slot(deadline)
            if wait_reason is not None:
                retry.update(dict.fromkeys(rest, wait_reason))
                break
            text = "\n".join(self.text(batch[i]) for i in chunk)
            outcome, reason, retry_after = self._post(text)
            if outcome == "sent":
                posted += 1
            elif outcome == "retry":
                retry.update(dict.fromkeys(rest, reason))
                break
            elif outcome == "reject_message":  # this message only (400 invalid_payload): the next may pass
                reject.update(dict.fromkeys(chunk, reason))
            else:  # the webhook is gone (403, 404, 410): no message will pass
                reject.update(dict.fromkeys(rest, reason))
                break
        if not retry and not reject:
            return None
        if len(retry) == len(batch):
            raise RetryableError(next(iter(retry.values())), retry_after=retry_after)
        if len(reject) == len(batch):
            raise RejectedError(next(iter(reject.values())))
        return SendOutcome(retry=retry, reject=reject, retry_after=retry_after)

    def _wait_for_slot(self, deadline: float) -> str | None:
        """Wait for the rate's next slot; why not, when that is past ``deadline``."""
        free_at = self._next_post_at
        now = time.monotonic()
        if free_at > deadline:
            return f"held back by rate {self.params.rate:g} message(s)/s: the rest of the batch follows ({self.url})"
        # The server's stop, once its grace is over, ends the wait: the records are retried.
        if free_at > now and self.stopping.wait(free_at - now):
            return f"destination stopping before its turn to post ({self.url})"
        return None

    def _post(self, text: str) -> tuple[str, str, float | None]:
        """POST one message: ("sent" | "retry" | "reject_message" | "reject_all", reason, Retry-After seconds)."""
        body = json.dumps({"text": text}, ensure_ascii=False).encode("utf-8")
        request = urllib.request.Request(
            self.params.webhook,
            data=body,
            headers={"Content-Type": "application/json; charset=utf-8", "User-Agent": "dc-destinations"},
            method="POST",
        )
        self._next_post_at = time.monotonic() + 1.0 / self.params.rate
        try:
            with self._opener.open(request, timeout=self.params.timeout) as response:
                response.read(_BODY_READ_LIMIT)
                return "sent", "", None
        except urllib.error.HTTPError as exc:
            status, reason = exc.code, exc.reason
            excerpt = self._excerpt(exc.read(_BODY_READ_LIMIT))
            retry_after = exc.headers.get("Retry-After") if exc.headers is not None else None
            exc.close()
        # ValueError: http.client.InvalidURL; HTTPException: an answer that is not HTTP (BadStatusLine).
        except (urllib.error.URLError, OSError, ValueError, http.client.HTTPException) as exc:
            detail = getattr(exc, "reason", None) or exc
            if isinstance(detail, TimeoutError) or isinstance(exc, TimeoutError):
                detail = f"no answer within {self.params.timeout:g} s"
            return "retry", self._scrub(f"cannot POST to the Slack webhook {self.url}: {detail}"), None
        message = self._scrub(f"Slack answered HTTP {status} {reason}" + (f": {excerpt}" if excerpt else ""))
        if status == 429:
            # Slack always means "slow down" by it: without a readable Retry-After, a second.
            seconds = retry_after_seconds(retry_after)
            delay = min(RETRY_AFTER_DEFAULT_S if seconds is None else seconds, RETRY_AFTER_MAX_S)
            return "retry", f"{message}; retrying after {delay:g} s ({self.url})", delay
        if is_retryable_status(status):
            return "retry", f"{message} ({self.url})", retry_after_seconds(retry_after)
        if status == 400:
            return "reject_message", f"{message} ({self.url})", None
        return "reject_all", f"{message} ({self.url})", None

    # -- messages ----------------------------------------------------------------------------------
    def _excerpt(self, data: bytes) -> str:
        return self._scrub(one_line(data.decode("utf-8", errors="replace"), _EXCERPT_CHARS))

    def _scrub(self, text: str) -> str:
        return masked(text, self._secrets)
