"""Kinesis Streams destination: records put into an Amazon Kinesis data stream with PutRecords.

Each batch from the destination server is split into PutRecords requests within the service's limits
(500 records and 5 MiB per request, 1 MiB per record including its partition key). The service answers
per record, so the outcome is per record too: records it failed (throughput exceeded, internal
failure) are retried alone, the others are confirmed; a record bigger than Kinesis accepts is rejected
alone. When a whole request fails — throttling, 5xx, network, and also a missing stream or refused
credentials, which an operator can fix while the buffer keeps the records — the records are retried.

Credentials come from boto3's default chain (environment, shared profile, instance or task role)
unless ``aws_access_key_id``/``aws_secret_access_key`` are given; with ``role_arn`` those are only used
to assume the role through STS, and the role's temporary credentials are refreshed before they expire.
The secret key is never logged nor quoted in an error.
"""

from __future__ import annotations

import datetime as dt
import re
import string
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import OutgoingRecord, ProbeResult, RejectedError, RetryableError, SendOutcome
from dc_core.params import param
from dc_core.records import MalformedRecord, dump_record
from dc_destinations.aws import CREDENTIAL_CODES, AwsClientParams, AwsDestination, BotoCoreError, ClientError
from dc_destinations.settings import time_key_param

# The service's limits (Kinesis Data Streams quotas): a record's data plus its partition key, and a
# PutRecords request's records and bytes (data plus partition keys).
MAX_RECORD_BYTES = 1024 * 1024
MAX_REQUEST_BYTES = 5 * 1024 * 1024
MAX_REQUEST_RECORDS = 500
MAX_PARTITION_KEY_CHARS = 256

# Whole-request errors that say the request itself is malformed: sending it again cannot help.
_REJECT_CODES = frozenset({"ValidationException", "InvalidArgumentException", "SerializationException"})
_STREAM_NAME = re.compile(r"[a-zA-Z0-9_.-]{1,128}")
_STREAM_ARN = re.compile(r"arn:aws[a-z-]*:kinesis:[a-z0-9-]+:\d{12}:stream/[a-zA-Z0-9_.-]{1,128}")
# Fluent Bit's sub-second extensions of strftime in time_key_format.
_FRACTIONS = {"%3N": 3, "%6N": 6, "%9N": 9, "%L": 9}


def _stream_problem(stream: str) -> str | None:
    ok = _STREAM_NAME.fullmatch(stream) or _STREAM_ARN.fullmatch(stream)
    return None if ok else "a stream name (letters, digits, '_', '-', '.'; 1 to 128) or a stream ARN"


def _template_fields(template: str) -> list[str]:
    """Names of the ``{key}`` fields of a partition key template; ValueError when it is not one."""
    names = []
    for _, name, spec, conversion in string.Formatter().parse(template):
        if name is None:
            continue
        if not name or spec or conversion or any(c in name for c in ".[]"):
            raise ValueError(name)
        names.append(name)
    return names


def _template_problem(template: str) -> str | None:
    try:
        _template_fields(template)
    except ValueError:
        return 'a template of top-level keys such as "{name}" or "{name}-{robot_id}" (\'{{\' for a brace)'
    return None if template else "a non-empty template"


@dataclass(frozen=True, kw_only=True)
class KinesisParams(AwsClientParams):
    stream: str = param(check=_stream_problem, doc="Name (or ARN) of the Kinesis data stream")
    partition_key: str = param(
        "{name}",
        check=_template_problem,
        doc="Partition key template over the record's top-level keys; the record_id when a key is missing",
    )
    time_key: str = time_key_param("The common time_key, read here for time_key_format (one value for both)")
    time_key_format: str = param(
        "", doc="strftime format (UTC; %3N, %6N, %9N, %L for fractions) of the time key; empty: time_format"
    )


class _Unsendable(Exception):
    """This record cannot be put into Kinesis as it is: rejected alone, with the reason."""


class KinesisStreams(AwsDestination[KinesisParams]):
    """Put records into an Amazon Kinesis data stream (PutRecords); failed records are retried alone."""

    service = "kinesis"

    def __init__(self, context: Any, params: KinesisParams) -> None:
        super().__init__(context, params, target=f"stream {params.stream}")
        self._fields = _template_fields(params.partition_key)

    # -- lifecycle -------------------------------------------------------------------------------
    def probe(self) -> ProbeResult:
        """DescribeStreamSummary with the real credentials: the stream exists and is writable-state."""
        try:
            summary = self._client.describe_stream_summary(StreamName=self.params.stream)["StreamDescriptionSummary"]
        except Exception as exc:  # botocore's errors and the network's; _describe words each
            _, message = self._describe(exc)
            code = str(getattr(exc, "response", {}).get("Error", {}).get("Code", ""))
            fix = "create the stream, or correct stream / region" if code == "ResourceNotFoundException" else ""
            return ProbeResult(False, message, fix or "check the credentials, region and endpoint")
        status = summary.get("StreamStatus", "")
        if status not in ("ACTIVE", "UPDATING"):
            return ProbeResult(False, f"{self.where} is {status}, not ACTIVE", "wait for the stream, or recreate it")
        return ProbeResult(True, f"{self.where} is {status}, credentials accepted")

    def on_activate(self) -> None:
        # The stream is not probed here: an unreachable service must not hold up activation, and the
        # first batch says clearly what is wrong.
        self.context.logger.info(f"putting records into {self.where}, partition key {self.params.partition_key!r}")

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        outcome = SendOutcome()
        requests: list[list[tuple[int, bytes, str]]] = [[]]
        request_bytes = 0
        for i, record in enumerate(batch):
            try:
                data, key = self._entry(record)
            except (_Unsendable, MalformedRecord) as exc:
                outcome.reject[i] = str(exc)
                continue
            size = len(data) + len(key.encode("utf-8"))
            if size > MAX_RECORD_BYTES:
                outcome.reject[i] = (
                    f"record of {size} bytes with its partition key, above Kinesis' {MAX_RECORD_BYTES} ({self.where})"
                )
                continue
            if len(requests[-1]) >= MAX_REQUEST_RECORDS or request_bytes + size > MAX_REQUEST_BYTES:
                requests.append([])
                request_bytes = 0
            requests[-1].append((i, data, key))
            request_bytes += size
        for n, entries in enumerate(requests):
            if not entries:
                continue
            try:
                results = self._put(entries)
            except RetryableError as exc:
                if n == 0 and not outcome.reject:
                    raise  # nothing of the batch went: the whole batch is retried
                # This request and the ones not sent yet are retried; those already put are confirmed.
                for later in requests[n:]:
                    outcome.retry.update((i, str(exc)) for i, _, _ in later)
                break
            except RejectedError as exc:
                outcome.reject.update((i, str(exc)) for i, _, _ in entries)
                continue
            for (i, _, _), result in zip(entries, results, strict=True):
                if result.get("ErrorCode"):
                    # Throughput exceeded, internal failure, a KMS hiccup: the service's per-record
                    # refusals all pass with time, so the record is retried alone.
                    outcome.retry[i] = f"{result['ErrorCode']}: {result.get('ErrorMessage', '')} ({self.where})"
        if outcome.retry or outcome.reject:
            return outcome
        return None

    def _entry(self, record: OutgoingRecord) -> tuple[bytes, str]:
        p = self.params
        data = record.data
        if p.time_key_format and p.time_key in data:
            data = {**data, p.time_key: _strftime(record.stamp_ns, p.time_key_format)}
        if p.log_key:
            if p.log_key not in data:
                raise _Unsendable(f"no key {p.log_key!r} (log_key) in the record")
            value = data[p.log_key]
            text = value if isinstance(value, str) else dump_record(value)
        else:
            text = record.to_json() if data is record.data else dump_record(data)
        # One record per line, as Fluent Bit's kinesis_streams output writes them: consumers that
        # concatenate records (Firehose to S3) keep them apart.
        return (text + "\n").encode("utf-8"), self._partition_key(record, data)

    def _partition_key(self, record: OutgoingRecord, data: dict[str, Any]) -> str:
        values: dict[str, str] = {}
        for name in self._fields:
            value = data.get(name)
            if value is None or value == "":
                return record.record_id
            values[name] = value if isinstance(value, str) else dump_record(value)
        key = self.params.partition_key.format_map(values)
        # Kinesis takes 1 to 256 characters; cut, not hashed, so the same record keeps the same shard.
        return key[:MAX_PARTITION_KEY_CHARS] or record.record_id

    def _put(self, entries: list[tuple[int, bytes, str]]) -> list[dict[str, Any]]:
        p = self.params
        target = {"StreamARN": p.stream} if p.stream.startswith("arn:") else {"StreamName": p.stream}
        try:
            response = self._client.put_records(
                Records=[{"Data": data, "PartitionKey": key} for _, data, key in entries], **target
            )
        except (BotoCoreError, ClientError) as exc:
            retryable, message = self._describe(exc)
            self._problem(message)
            if retryable:
                raise RetryableError(message) from None
            raise RejectedError(message) from None
        self._works_again("records accepted")
        results: list[dict[str, Any]] = response.get("Records", [])
        if len(results) != len(entries):
            raise RetryableError(
                f"PutRecords answered {len(results)} results for {len(entries)} records ({self.where})"
            )
        return results

    # -- messages ----------------------------------------------------------------------------------
    def _describe(self, exc: Exception) -> tuple[bool, str]:
        """Whether a whole-request failure may pass, and what to tell the operator."""
        common = self.params.common_failure(exc, "Kinesis", self.where)
        if common is not None:
            return True, common
        if isinstance(exc, ClientError):
            error = exc.response.get("Error", {})
            code, text = str(error.get("Code", "")), str(error.get("Message", ""))
            status = exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0)
            if code == "ResourceNotFoundException":
                return True, self.params.scrub(f"no {self.where}: create it or correct `stream` / `region` ({text})")
            if code in CREDENTIAL_CODES:
                return True, self.params.scrub(
                    f"AWS refused the credentials for {self.where}: {code}: {text} "
                    "(check the access key, role_arn and the policy's kinesis:PutRecords)"
                )
            if code in _REJECT_CODES:
                return False, self.params.scrub(f"Kinesis refused the request: {code}: {text} ({self.where})")
            return True, self.params.scrub(f"PutRecords failed: {code or status}: {text} ({self.where})")
        return True, self.params.scrub(f"PutRecords failed: {type(exc).__name__}: {exc} ({self.where})")


def _strftime(stamp_ns: int, fmt: str) -> str:
    seconds, nanos = divmod(stamp_ns, 1_000_000_000)
    for token, digits in _FRACTIONS.items():
        fmt = fmt.replace(token, f"{nanos:09d}"[:digits])
    return dt.datetime.fromtimestamp(seconds, tz=dt.UTC).strftime(fmt)
