"""InfluxDB destination: each batch written as line protocol, one POST to the v1 or v2 write API.

DC writes the line protocol itself rather than through a client library: the rules are short, and
owning them lets a refused point be traced back to its record. Each record is one point, shaped as a
Telegraf user expects: the measurement is ``measurement_prefix`` + the record's ``name`` (or the
``measurement`` parameter), ``tag_keys`` (and with ``auto_tags`` the record's top-level text values)
become tags, every other value a field — nested objects and arrays flattened to ``cpu.average``,
``sorted.0.pid``, a flattened record's JSON pointers (``/cpu/average``) the same way —, DC's
bookkeeping keys (``record_id``, the time key…) are left out, command lines are cut, and the time is
the record's stamp in nanoseconds.

InfluxDB writes the valid points of a batch and refuses the others with ``400 partial write``; its
message names the first refused line or field. Those records are rejected alone and the rest is sent
again to confirm it (writing a point again with the same series and time only overwrites it with the
same values); when the message does not tell which lines failed, the batch is sent line by line.
Credentials (basic password, v2 token) are secrets: never logged, masked should a server echo them.
"""

from __future__ import annotations

import base64
import contextlib
import gzip
import http.client
import json
import math
import re
import ssl
import urllib.parse
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import (
    ConfigurationProblem,
    Destination,
    OutgoingRecord,
    ProbeResult,
    RejectedError,
    RetryableError,
    SendOutcome,
)
from dc_core.errors import ConfigError
from dc_core.params import host_param, param, port_problem, url_host
from dc_core.records import measurement_of
from dc_destinations.http_client import HttpConnection, is_retryable_status, one_line, retry_after_seconds
from dc_destinations.tls import TlsParams, client_context, warn_if_credentials_in_clear

APIS = ("auto", "v1", "v2")
_INT64 = (-(2**63), 2**63 - 1)
_EXCERPT_CHARS = 300
# Points remembered to give simultaneous records distinct sequence tags (see Sequencer).
_SEQUENCE_MEMORY = 10_000
# Statuses of a write refused for some of its points (v1: 400; v2 also 422 for schema conflicts).
_POINT_ERRORS = frozenset({400, 422})
_TYPE_CONFLICT = re.compile(r'input field \\?"(.+?)\\?" on measurement \\?"(.+?)\\?" is type (\w+)')
_INVALID_FIELD = re.compile(r'invalid field name: input field \\?"(.+?)\\?" on measurement \\?"(.+?)\\?"')
_UNPARSABLE = re.compile(r"unable to parse '(.*?)': ", re.DOTALL)
CONTENT_ENCODINGS = ("gzip", "identity")
# Keys DC adds to records for its own sake: the destination's time key (the point has its time), the
# measurement server's shape flags, the id the buffer deduplicates with, the routing tags.
BOOKKEEPING_KEYS = ["date", "flattened", "nested", "record_id", "schema_version", "tags"]
# Keys holding a process's command line (Cpu's processes: sorted.N.cmd): arguments may hold secrets.
COMMAND_LINE_KEYS = ["cmd", "cmdline", "command_line"]
# Never tagged by auto_tags: a run is a value that changes at every start (a tag would add a series
# per run); tag_keys: [run_id] makes it one as the original did.
_NEVER_AUTO_TAGGED = frozenset({"run_id"})


@dataclass(frozen=True, kw_only=True, repr=False)
class InfluxDBParams(TlsParams):
    host: str = host_param("the InfluxDB server")
    port: int = param(8086, check=port_problem, doc="TCP port of the InfluxDB HTTP API")
    api: str = param(
        "auto", choices=APIS, doc="v1: /write with a database; v2: /api/v2/write with org and bucket; auto: v2 when "
        "bucket or http_token is set"
    )  # fmt: skip
    database: str = param("fluentbit", doc="Database the points are written to (v1 API)")
    bucket: str = param("", doc="Bucket the points are written to (v2 API); a v1 `database/retention` works on 1.8+")
    org: str = param("fluent", doc="Organization of the bucket (v2 API)")
    measurement: str = param("", doc="Measurement of every point; empty: measurement_prefix + the record's `name`")
    measurement_prefix: str = param(
        "dc_", doc="Put before the record's `name` (`dc_cpu`), so that DC's never mix with Telegraf's (`cpu`); "
        '"": the original\'s names'
    )  # fmt: skip
    tag_keys: list[str] | str = param([], doc="Record keys written as tags (a list, or names separated by spaces)")
    auto_tags: bool = param(
        False, doc="Write the record's top-level text values as tags too (Fluent Bit's auto_tags), but for run_id, "
        "the bookkeeping keys, command lines and a flattened record's keys"
    )  # fmt: skip
    bookkeeping_fields: bool = param(
        False, doc="Write bookkeeping_keys as fields too (the original wrote them on every point)"
    )
    bookkeeping_keys: list[str] = param(
        BOOKKEEPING_KEYS,
        doc="DC's own keys, left out of the points unless bookkeeping_fields (add a time_key of yours)",
    )
    pointer_field_names: bool = param(
        False, doc="Keep a flattened record's JSON-pointer keys (`/cpu/average`) as field names, as the original"
    )
    command_line_chars: int = param(
        64, minimum=-1, doc="Characters of a command line kept (the rest cut, marked with …); 0: not written; -1: whole"
    )
    command_line_keys: list[str] = param(COMMAND_LINE_KEYS, doc="Keys (their last part) holding command lines")
    content_encoding: str = param(
        "gzip", choices=CONTENT_ENCODINGS, doc="gzip: compressed writes (Telegraf's default); identity: plain"
    )
    sequence_tag: str = param(
        "_seq", doc="Tag numbering records of the same series and time, which would overwrite each other; empty: none"
    )
    separator: str = param(".", doc="Joins the keys of nested objects and array indexes into field names")
    http_user: str = param("", doc="User of HTTP basic authentication; empty: none")
    http_passwd: str = param("", secret=True, aliases=("http_password",), doc="Password of http_user (never logged)")
    http_token: str = param("", secret=True, doc="Token sent as `Authorization: Token <token>` (v2; never logged)")
    timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds to connect and for each read or write")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.http_passwd and not self.http_user:
            raise ConfigError("http_passwd", "set http_user too (basic authentication needs both)")
        if ":" in self.http_user:
            raise ConfigError("http_user", "a user name without ':' (basic authentication separates with it)")
        if self.http_token and any(c.isspace() for c in self.http_token):
            raise ConfigError("http_token", "expected a token without spaces")
        if self.api_version == "v1" and not self.database:
            raise ConfigError("database", "expected a database name (the v1 API writes to a database)")
        if self.api_version == "v2" and not (self.bucket and self.org):
            raise ConfigError("bucket", "expected a bucket and an org (the v2 API writes to a bucket)")
        if not self.separator or any(c in self.separator for c in "\\\n\r"):
            raise ConfigError("separator", "expected a non-empty text without backslash or line break")
        for key in self.tag_list:
            if "\n" in key or "\r" in key:
                raise ConfigError("tag_keys", "expected key names without line breaks")
        if _identifier_problem(self.sequence_tag):
            raise ConfigError("sequence_tag", f"expected a tag name: {_identifier_problem(self.sequence_tag)}")
        if self.measurement and _identifier_problem(self.measurement, measurement=True):
            raise ConfigError("measurement", f"expected a measurement name: {_identifier_problem(self.measurement)}")
        prefix_problem = _identifier_problem(self.measurement_prefix, measurement=True) or (
            "a space, comma or double quote (a name a query must quote)"
            if re.search(r"[\s,\"]", self.measurement_prefix)
            else None
        )
        if prefix_problem:
            raise ConfigError(
                "measurement_prefix", f"expected the start of a measurement name, without {prefix_problem}"
            )

    @property
    def api_version(self) -> str:
        if self.api != "auto":
            return self.api
        return "v2" if self.bucket or self.http_token else "v1"

    @property
    def tag_list(self) -> list[str]:
        return self.tag_keys.split() if isinstance(self.tag_keys, str) else list(self.tag_keys)


# -- line protocol ---------------------------------------------------------------------------------


class LineError(ValueError):
    """A record that cannot be written as a point; the message says why."""


def _identifier_problem(text: str, *, measurement: bool = False) -> str | None:
    """What line protocol cannot carry in a measurement, tag or field name or a tag value."""
    if "\n" in text or "\r" in text:
        return "a line break"
    # A backslash is kept as written, except before a separator, where it would escape the separator.
    if text.endswith("\\") or re.search(r"\\[ ,=]", text):
        return "a backslash before a space, comma or '=' or at the end"
    if measurement and text.startswith("#"):
        return "a leading '#' (a comment line)"
    return None


def escape_measurement(name: str) -> str:
    return name.replace(",", "\\,").replace(" ", "\\ ")


def escape_key(text: str) -> str:
    """A tag key, tag value or field key: commas, equals signs and spaces escaped."""
    return text.replace(",", "\\,").replace("=", "\\=").replace(" ", "\\ ")


def escape_string(text: str) -> str:
    """A string field value, quoted: backslashes and double quotes escaped (line breaks may stay)."""
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def field_value(value: Any) -> str | None:
    """A field value as line protocol; None for what InfluxDB cannot store (null, NaN, infinities)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        if not _INT64[0] <= value <= _INT64[1]:
            raise LineError(f"the integer {value} does not fit InfluxDB's 64-bit integers")
        return f"{value}i"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else None
    if isinstance(value, str):
        return escape_string(value)
    return None


def flatten(value: Any, prefix: str, separator: str) -> Iterator[tuple[str, Any]]:
    """(key, scalar) pairs of a nested value: object keys and array indexes joined by ``separator``."""
    if isinstance(value, dict):
        for key, inner in value.items():
            yield from flatten(inner, f"{prefix}{separator}{key}" if prefix else str(key), separator)
    elif isinstance(value, (list, tuple)):
        for index, inner in enumerate(value):
            yield from flatten(inner, f"{prefix}{separator}{index}" if prefix else str(index), separator)
    else:
        yield prefix, value


def _tag_value(value: Any) -> str | None:
    if value is None or value == "":
        return None  # line protocol has no empty tag value: the tag is left out
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(",", ":"), ensure_ascii=False, sort_keys=True)
    return str(value)


def _safe_key(key: str) -> str:
    # InfluxDB refuses a field or tag named "time" (the point's own time), Uptime's for one.
    return "time_" if key == "time" else key


@dataclass(frozen=True)
class Point:
    """One record as line protocol, in parts: the series (measurement and tags) and the rest."""

    measurement: str
    tags: tuple[tuple[str, str], ...]
    fields: tuple[tuple[str, str], ...]
    stamp_ns: int

    def line(self, sequence_tag: str = "", sequence: int = 0) -> str:
        tags = list(self.tags)
        if sequence:
            tags = sorted([*tags, (sequence_tag, str(sequence))])
        series = escape_measurement(self.measurement) + "".join(f",{escape_key(k)}={escape_key(v)}" for k, v in tags)
        fields = ",".join(f"{escape_key(k)}={v}" for k, v in self.fields)
        return f"{series} {fields} {self.stamp_ns}"

    def field_type(self, key: str) -> str | None:
        """InfluxDB's name of the type of field ``key``, None when the point has no such field."""
        for name, value in self.fields:
            if name == key:
                if value.endswith("i") and not value.startswith('"'):
                    return "integer"
                if value in ("true", "false"):
                    return "boolean"
                return "string" if value.startswith('"') else "float"
        return None


def to_point(record: OutgoingRecord, params: InfluxDBParams) -> Point:
    """The record as a point; :class:`LineError` when it has nothing to write or cannot be written."""
    data = record.data
    measurement = params.measurement
    if not measurement:
        name = data.get("name")
        if not isinstance(name, str) or not name:
            # Without a name (a measurement that does not include it), the last part of its topic.
            name = measurement_of(record.topic) or "dc"
        measurement = params.measurement_prefix + name
    _check(measurement, "the measurement", measurement=True)
    name_key = "" if params.measurement else "name"
    tag_keys = set(params.tag_list)
    left_out = set() if params.bookkeeping_fields else set(params.bookkeeping_keys) - tag_keys
    tags: dict[str, str] = {}
    fields: list[tuple[str, str]] = []
    for key, value in data.items():
        if (key == name_key and params.measurement_prefix + str(value) == measurement) or key in left_out:
            continue  # the measurement already, or DC's bookkeeping
        pointer = key.startswith("/") and not params.pointer_field_names
        if key in tag_keys or (
            params.auto_tags
            and isinstance(value, str)
            and not key.startswith("/")
            and key not in _NEVER_AUTO_TAGGED
            and key not in params.bookkeeping_keys
            and key not in params.command_line_keys
            and not _identifier_problem(value)
        ):
            tag = _tag_value(value)
            if tag is not None:
                _check(key, f"the tag key {key!r}")
                _check(tag, f"the value of tag {key!r}")
                tags[_safe_key(key)] = tag
            continue
        start = _from_pointer(key, params.separator) if pointer else key
        for field_key, scalar in flatten(value, start, params.separator):
            if isinstance(scalar, str) and params.command_line_chars >= 0 and _last_part(field_key, params):
                if params.command_line_chars == 0:
                    continue
                if len(scalar) > params.command_line_chars:
                    scalar = scalar[: params.command_line_chars] + "…"
            text = field_value(scalar)
            if text is None:
                continue
            _check(field_key, f"the field key {field_key!r}")
            fields.append((_safe_key(field_key), text))
    if not fields:
        raise LineError("the record has no field InfluxDB can store (every value is a tag, null or empty)")
    # Sorted tags: InfluxDB's advice for the fastest writes, and the same series key for every record.
    return Point(measurement, tuple(sorted(tags.items())), tuple(fields), record.stamp_ns)


def _from_pointer(key: str, separator: str) -> str:
    """A flattened record's key as Telegraf names fields: ``/cpu/average`` -> ``cpu.average``."""
    return separator.join(part.replace("~1", "/").replace("~0", "~") for part in key[1:].split("/"))


def _last_part(field_key: str, params: InfluxDBParams) -> bool:
    """Whether the field holds a command line (its key's last part is one of command_line_keys)."""
    return field_key.rsplit(params.separator, 1)[-1] in params.command_line_keys


def _check(text: str, what: str, *, measurement: bool = False) -> None:
    problem = _identifier_problem(text, measurement=measurement)
    if problem:
        raise LineError(f"{what} holds {problem}, which line protocol cannot carry")


class Sequencer:
    """Numbers records that share a series and a time, which InfluxDB would otherwise merge into one point.

    The first record of a series and time gets no sequence tag (most records: their points look as
    without the feature); the next distinct records get 1, 2, … A record sent again (a retry) keeps
    its number, so writing it again overwrites its own point. The last ``_SEQUENCE_MEMORY`` points
    are remembered, in this process only.
    """

    def __init__(self) -> None:
        self._seen: OrderedDict[tuple[str, tuple[tuple[str, str], ...], int], dict[str, int]] = OrderedDict()

    def number(self, point: Point, record_id: str) -> int:
        key = (point.measurement, point.tags, point.stamp_ns)
        ids = self._seen.get(key)
        if ids is None:
            ids = self._seen[key] = {}
            if len(self._seen) > _SEQUENCE_MEMORY:
                self._seen.popitem(last=False)
        else:
            self._seen.move_to_end(key)
        return ids.setdefault(record_id, len(ids))


# -- the destination --------------------------------------------------------------------------------


class InfluxDB(Destination[InfluxDBParams]):
    """Write records as points to InfluxDB (v1 /write or v2 /api/v2/write, line protocol, ns precision)."""

    def __init__(self, context: Any, params: InfluxDBParams) -> None:
        super().__init__(context, params)
        self._connection: HttpConnection | None = None
        self._tls: ssl.SSLContext | None = None  # for the probe's own connection
        self._headers: list[tuple[str, str]] = []
        self._secrets: list[str] = []
        self._sequencer = Sequencer()
        self.path = ""
        self.url = ""

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        p = self.params
        if p.api_version == "v2":
            query = {"org": p.org, "bucket": p.bucket, "precision": "ns"}
            self.path = "/api/v2/write?" + urllib.parse.urlencode(query)
        else:
            self.path = "/write?" + urllib.parse.urlencode({"db": p.database, "precision": "ns"})
        host = url_host(p.host)
        self.url = f"{'https' if p.tls_on else 'http'}://{host}:{p.port}{self.path}"
        tls = self._tls = client_context(p, f"destination_server.{self.context.name}", self.context.logger)
        self._headers = [("Content-Type", "text/plain; charset=utf-8"), ("User-Agent", "dc-destinations")]
        if p.content_encoding == "gzip":
            self._headers.append(("Content-Encoding", "gzip"))
        if p.http_token:
            self._headers.append(("Authorization", f"Token {p.http_token}"))
            self._secrets = [p.http_token]
        elif p.http_user:
            token = base64.b64encode(f"{p.http_user}:{p.http_passwd}".encode()).decode("ascii")
            self._headers.append(("Authorization", f"Basic {token}"))
            self._secrets = [s for s in (p.http_passwd, token) if s]
        if p.tls_key_passwd:
            self._secrets.append(p.tls_key_passwd)
        what = "cannot write to InfluxDB at"
        connection = HttpConnection(p.host, p.port, timeout=p.timeout, tls=tls, where=self.url, what=what)
        connection.secrets = self._secrets
        self._connection = self.keep(connection)
        warn_if_credentials_in_clear(
            self.context.logger,
            self.context.name,
            p.host,
            credentials="the token" if p.http_token else (f"the password of {p.http_user}" if p.http_passwd else ""),
            verified_tls=p.tls_verified,
            fix="set tls: true with tls_verify: true (tls_ca_file for a private CA)"
            if not p.tls_on
            else "set tls_verify: true (tls_ca_file for a private CA)",
        )

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a server that is down
        # must not hold up activation.
        self.context.logger.info(f"writing points to {self.url} (InfluxDB {self.params.api_version} API)")

    # -- sending -----------------------------------------------------------------------------------
    def lines(self, batch: Sequence[OutgoingRecord]) -> tuple[dict[int, str], dict[int, str]]:
        """The line of each record that can be written, and the reason of each that cannot (by index)."""
        lines: dict[int, str] = {}
        rejected: dict[int, str] = {}
        for index, record in enumerate(batch):
            try:
                point = to_point(record, self.params)
            except LineError as exc:
                rejected[index] = str(exc)
                continue
            sequence = self._sequencer.number(point, record.record_id) if self.params.sequence_tag else 0
            lines[index] = point.line(self.params.sequence_tag, sequence)
        return lines, rejected

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        pending, rejected = self.lines(batch)
        retry: dict[int, str] = {}
        isolate = False
        # Each round either confirms what is pending or takes at least one record out of it.
        while pending:
            if isolate:
                for index, line in pending.items():
                    status, message = self._write([line])
                    if status in _POINT_ERRORS:
                        rejected[index] = message
                    elif status >= 300:
                        retry[index] = message
                break
            status, message = self._write(list(pending.values()))
            if status < 300:
                break
            refused = _refused_lines(message, pending, self._points_cache(batch, pending))
            if refused:
                for index in refused:
                    rejected[index] = message
                    del pending[index]
            else:
                # InfluxDB did not say which line it refused: one request per line tells.
                isolate = True
        if not rejected and not retry:
            return None
        return SendOutcome(retry=retry, reject=rejected)

    def _points_cache(self, batch: Sequence[OutgoingRecord], pending: dict[int, str]) -> dict[int, Point]:
        points: dict[int, Point] = {}
        for index in pending:
            with contextlib.suppress(LineError):
                points[index] = to_point(batch[index], self.params)
        return points

    def _write(self, lines: list[str]) -> tuple[int, str]:
        """POST the lines: (status, message) for a refused write, raising for whole-batch failures."""
        assert self._connection is not None, "send() before on_configure()"
        body = ("\n".join(lines) + "\n").encode("utf-8")
        if self.params.content_encoding == "gzip":
            # Level 1: most of the gain (line protocol repeats its keys) for a fraction of level 9's CPU.
            body = gzip.compress(body, compresslevel=1, mtime=0)
        answer = self._connection.post(self.path, self._headers, body)
        status = answer.status
        if 200 <= status < 300:
            return status, ""
        error = self._connection.scrub(_server_error(answer.body.decode("utf-8", errors="replace")))
        message = f"HTTP {status} {answer.reason}" + (f": {error}" if error else "") + f" ({self.url})"
        p = self.params
        if status in (401, 403):
            who = f"sent user {p.http_user!r}" if p.http_user and not p.http_token else "sent a token"
            if not p.http_user and not p.http_token:
                who = "sent no credentials"
            hint = "http_token" if p.api_version == "v2" else "http_user and http_passwd"
            # Retried: credentials are fixed on the server or in the parameters, and the records wait.
            raise ConfigurationProblem(
                f"InfluxDB refused the credentials: {message} (check {hint}; {who})", fix=f"check {hint}"
            )
        if status == 404:
            if p.api_version == "v1":
                raise ConfigurationProblem(
                    f"InfluxDB database {p.database!r} not found: {message} (create it: CREATE DATABASE {p.database})",
                    fix=f"create the database (CREATE DATABASE {p.database}) or correct `database`",
                )
            raise ConfigurationProblem(
                f"InfluxDB bucket {p.bucket!r} of org {p.org!r} not found, or no v2 API on this server "
                f"(InfluxDB 1.x before 1.8: set api: v1): {message}",
                fix="create the bucket, or correct bucket / org / api",
            )
        if is_retryable_status(status):
            raise RetryableError(message, retry_after=retry_after_seconds(answer.retry_after))
        if status in _POINT_ERRORS:
            return status, message
        raise RejectedError(message)

    def probe(self) -> ProbeResult:
        """A read with the real credentials: v2 lists the bucket by name, v1 the databases.

        Over a connection of its own, closed after: the kept one is left to ``send``.
        """
        p = self.params
        if p.api_version == "v2":
            query = urllib.parse.urlencode({"name": p.bucket, "org": p.org} if p.org else {"name": p.bucket})
            path, target = f"/api/v2/buckets?{query}", f"bucket {p.bucket!r}"
        else:
            path, target = "/query?" + urllib.parse.urlencode({"q": "SHOW DATABASES"}), f"database {p.database!r}"
        own = HttpConnection(
            p.host, p.port, timeout=p.timeout, tls=self._tls, where=self.url, what="cannot read from InfluxDB at"
        )
        own.secrets = self._secrets
        headers = {name: value for name, value in self._headers if name.lower() != "content-type"}
        try:
            connection = own.get()
            connection.request("GET", path, headers=headers)
            response = connection.getresponse()
            status, text = response.status, response.read(1 << 20).decode("utf-8", errors="replace")
        except (OSError, http.client.HTTPException) as exc:
            return ProbeResult(False, own.failure(own.what, exc), "check host, port and tls")
        finally:
            own.close()
        hint = "http_token" if p.api_version == "v2" else "http_user and http_passwd"
        if status in (401, 403):
            return ProbeResult(False, f"InfluxDB refused the credentials: HTTP {status} ({self.url})", f"check {hint}")
        if status != 200:
            error = own.scrub(_server_error(text))
            return ProbeResult(False, f"InfluxDB answered HTTP {status}: {error} ({self.url})", "check api, org")
        if f'"{p.bucket if p.api_version == "v2" else p.database}"' not in text:
            create = "create the bucket" if p.api_version == "v2" else f"CREATE DATABASE {p.database}"
            return ProbeResult(False, f"no {target} in InfluxDB {p.host}:{p.port}", f"{create}, or correct the name")
        return ProbeResult(True, f"{target} found, credentials accepted ({p.host}:{p.port})")


def _server_error(text: str) -> str:
    """The message of an InfluxDB error answer (v1 ``{"error": …}``, v2 ``{"message": …}``), else the text."""
    try:
        answer = json.loads(text)
    except ValueError:
        answer = None
    if isinstance(answer, dict):
        found = answer.get("error") or answer.get("message")
        if isinstance(found, str):
            text = found
    return one_line(text, _EXCERPT_CHARS)


def _refused_lines(message: str, pending: dict[int, str], points: dict[int, Point]) -> list[int]:
    """Indexes of the lines InfluxDB's message names: a line it could not parse, or the points with
    the field (name and type) it refused. Empty when it names none of them."""
    refused: set[int] = set()
    for match in _UNPARSABLE.finditer(message):
        quoted = match.group(1)
        refused.update(i for i, line in pending.items() if " ".join(line.split()) == quoted)
    conflict = _TYPE_CONFLICT.search(message)
    if conflict:
        field, measurement, kind = conflict.groups()
        refused.update(
            i for i, point in points.items() if point.measurement == measurement and point.field_type(field) == kind
        )
    invalid = _INVALID_FIELD.search(message)
    if invalid:
        field, measurement = invalid.groups()
        refused.update(
            i for i, point in points.items() if point.measurement == measurement and point.field_type(field) is not None
        )
    return sorted(refused)
