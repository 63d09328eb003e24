"""S3 destination: each batch of records written as an object of JSON lines to Amazon S3 or an S3-compatible store.

In DC the destination server's buffer already gathers records into batches (``batch_size``, every
``flb.flush`` seconds) and keeps them until they are confirmed, so this plugin holds nothing itself:
one ``send()`` writes its batch as one object (several when the batch is larger than
``total_file_size``) and returns only once S3 has it. Fluent Bit's local staging folder
(``store_dir``) and upload timer (``upload_timeout``) have no role left and are accepted for
compatibility only.

A retried batch must not leave a second copy behind: the object key's ``$UUID`` (and the suffix
added when the key has none) is derived from the object's first ``record_id``, and the key's time
from that record's stamp, so an upload retried after a failure — or after a success whose answer
was lost — writes the same key again and replaces the object instead of adding one.

Credentials come from boto3's default chain unless ``aws_access_key_id``/``aws_secret_access_key``
are given; with ``role_arn`` those only assume the role through STS. Refused credentials and a
missing bucket are retried like a network failure — an operator can fix them while the buffer keeps
the records — with a message naming the bucket and endpoint, never the secret key.
"""

from __future__ import annotations

import base64
import contextlib
import gzip
import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import ConfigurationProblem, OutgoingRecord, ProbeResult, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import compat_param, param
from dc_core.paths import expand_time
from dc_core.records import MalformedRecord, dump_record
from dc_destinations.aws import (
    CREDENTIALS_MISSING,
    MAX_PART_BYTES,
    MAX_PARTS,
    MIN_PART_BYTES,
    S3_CREDENTIAL_CODES,
    AwsClientParams,
    AwsDestination,
    BotoCoreError,
    ClientError,
    bucket_problem,
    size_problem,
)
from dc_destinations.object_files import record_metadata
from dc_destinations.s3 import parquet
from dc_destinations.settings import parse_size

CANNED_ACLS = (
    "",
    "private",
    "public-read",
    "public-read-write",
    "authenticated-read",
    "aws-exec-read",
    "bucket-owner-read",
    "bucket-owner-full-control",
)
STORAGE_CLASSES = (
    "",
    "STANDARD",
    "REDUCED_REDUNDANCY",
    "STANDARD_IA",
    "ONEZONE_IA",
    "INTELLIGENT_TIERING",
    "GLACIER",
    "GLACIER_IR",
    "DEEP_ARCHIVE",
    "OUTPOSTS",
    "SNOW",
    "EXPRESS_ONEZONE",
)
_TAG_PART = re.compile(r"\$TAG\[(\d+)\]")
_DURATION = re.compile(r"(\d+(?:\.\d+)?)\s*([smhd]?)", re.IGNORECASE)


def _duration_problem(text: str) -> str | None:
    return None if _DURATION.fullmatch(text.strip()) else 'a duration such as "10m", "60s" or "1h"'


def _key_format_problem(text: str) -> str | None:
    return None if text.strip("/") else 'a key format such as "/fluent-bit-logs/$TAG/%Y/%m/%d/%H/%M/%S"'


@dataclass(frozen=True, kw_only=True)
class S3Params(AwsClientParams):
    bucket: str = param(check=bucket_problem, doc="Bucket the objects are written to (it must exist)")
    s3_key_format: str = param(
        "/fluent-bit-logs/$TAG/%Y/%m/%d/%H/%M/%S",
        check=_key_format_problem,
        doc="Object key: $TAG, $TAG[n], $UUID, $INDEX and strftime of the first record's time (UTC)",
    )
    s3_key_format_tag_delimiters: str = param(".", doc="Characters that split $TAG into $TAG[0], $TAG[1]…")
    static_file_path: bool = param(False, doc="Do not append -$UUID to a key format without $UUID")
    total_file_size: str = param("100M", check=size_problem, doc="Most bytes (before compression) of one object")
    upload_chunk_size: str = param(
        "50M", check=size_problem, doc="Objects above this size are uploaded in parts of this size (5M to 5G)"
    )
    use_put_object: bool = param(False, doc="Always one PutObject request, never a multipart upload")
    upload_timeout: str = compat_param(
        "10m",
        "each batch is written when the destination server sends it (flb.flush, batch_size)",
        check=_duration_problem,
    )
    store_dir: str = compat_param("/tmp/fluent-bit/s3", "the destination server's buffer keeps the records")
    store_dir_limit_size: str = compat_param(
        "0", "the destination server's buffer keeps the records (storage_total_limit_size bounds it)"
    )
    preserve_data_ordering: bool = compat_param(True, "batches are always sent in order")
    format: str = param(
        "json",
        choices=("json", "parquet"),
        doc="json: objects of JSON lines; parquet: one Parquet table (zstd) per batch and measurement",
    )
    compression: str = param(
        "",
        choices=("", "gzip", "arrow", "parquet"),
        doc="gzip: compressed JSON lines (.gz, Content-Encoding: gzip); arrow or parquet (the original's): "
        "format: parquet",
    )
    measurement_schemas: dict[str, str] = param(
        default_factory=dict,
        doc="With format: parquet, the JSON schema typing the columns of each measurement name: a measurement "
        "plugin type (dc_measurements/Cpu) or a schema file; a name not listed: the plugin type it names, if any",
    )
    content_type: str = param("", doc="Content-Type of the objects; empty: application/x-ndjson")
    canned_acl: str = param("", choices=CANNED_ACLS, doc="Canned ACL of the objects; empty: the bucket's default")
    storage_class: str = param("", choices=STORAGE_CLASSES, doc="Storage class of the objects; empty: STANDARD")
    send_content_md5: bool = param(False, doc="Send Content-MD5 with each request (buckets with object lock)")
    # An object takes longer than a Kinesis request: AwsClientParams' timeout with S3's default.
    timeout: float = param(30.0, minimum=0.1, maximum=3600, doc="Seconds to connect and for each read")

    @property
    def parquet(self) -> bool:
        return self.format == "parquet" or self.compression in ("arrow", "parquet")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.parquet:
            if self.format == "parquet" and self.compression == "gzip":
                raise ConfigError("compression", "gzip is for JSON lines: Parquet objects are zstd-compressed inside")
            if self.log_key:
                raise ConfigError("log_key", "writes one key per line: not with format: parquet")
            missing = parquet.pyarrow_missing()
            if missing is not None:
                raise ConfigError("format", missing)
            parquet.MeasurementSchemas(self.measurement_schemas, "measurement_schemas")
        chunk = parse_size(self.upload_chunk_size) or 0
        if not MIN_PART_BYTES <= chunk <= MAX_PART_BYTES:
            raise ConfigError(
                "upload_chunk_size", f'expected 5M to 5G (S3\'s part sizes), got "{self.upload_chunk_size}"'
            )


# An object to write: the batch indexes of its records, its bytes, its measurement's name ($NAME).
_Object = tuple[list[int], bytes, str]


def _key_part(name: str) -> str:
    """A measurement's name as one part of a key: no "/" (it would add a folder), never empty."""
    return name.replace("/", "_") or "unnamed"


class _Unsendable(Exception):
    """This record cannot be written as a line: rejected alone, with the reason."""


class S3(AwsDestination[S3Params]):
    """Write each batch of records as an object of JSON lines to Amazon S3 or an S3-compatible store."""

    service = "s3"

    def __init__(self, context: Any, params: S3Params) -> None:
        super().__init__(context, params, target=f"bucket {params.bucket}")
        self._max_object_bytes = parse_size(params.total_file_size) or 0
        self._chunk_bytes = parse_size(params.upload_chunk_size) or MIN_PART_BYTES
        self._tag_parts = self._split_tag(context.name)
        self._schemas = parquet.MeasurementSchemas(params.measurement_schemas, "measurement_schemas")

    def _split_tag(self, tag: str) -> list[str]:
        delimiters = self.params.s3_key_format_tag_delimiters
        parts = re.split(f"[{re.escape(delimiters)}]", tag) if delimiters else [tag]
        for match in _TAG_PART.finditer(self.params.s3_key_format):
            if int(match.group(1)) >= len(parts):
                raise ConfigError(
                    "s3_key_format",
                    f"{match.group(0)} is beyond the {len(parts)} part(s) of the tag {tag!r} "
                    f"split at {delimiters!r} (s3_key_format_tag_delimiters)",
                )
        return parts

    # -- lifecycle -------------------------------------------------------------------------------
    def probe(self) -> ProbeResult:
        """HEAD of the bucket with the real credentials: it exists and they may see it (a write
        permission is only proven by dc check --write-test)."""
        try:
            self._client.head_bucket(Bucket=self.params.bucket)
        except (BotoCoreError, ClientError) as exc:
            fix = _fix_for(exc)
            code = str(getattr(exc, "response", {}).get("Error", {}).get("Code", ""))
            if code in ("404", "NoSuchBucket"):
                return ProbeResult(
                    False, f"no {self.where}", "create the bucket, or correct bucket / region / endpoint"
                )
            if code == "403":  # a HEAD answer has no body, hence no error code but the status
                fix = "check the access key, secret key, role_arn and the policy's s3:ListBucket"
            return ProbeResult(False, self._describe(exc, "(HEAD bucket)"), fix or "check endpoint and region")
        return ProbeResult(True, f"{self.where} exists, credentials accepted")

    def on_activate(self) -> None:
        # The bucket is not probed here: an unreachable store must not hold up activation, and the
        # first batch says clearly what is wrong.
        self.context.logger.info(f"writing objects to {self.where}, keys {self.params.s3_key_format!r}")

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        outcome = SendOutcome()
        objects = self._parquet_objects(batch, outcome) if self.params.parquet else self._json_objects(batch, outcome)
        for n, (indexes, body, name) in enumerate(objects):
            key = self.object_key(batch[indexes[0]], n, name)
            try:
                self._upload(key, body, record_metadata([batch[i] for i in indexes]))
            except RetryableError as exc:
                if n == 0 and not outcome.reject:
                    raise  # nothing of the batch went: the whole batch is retried
                # This object and the ones not written yet are retried; those written are confirmed.
                for later, _, _ in objects[n:]:
                    outcome.retry.update((i, str(exc)) for i in later)
                break
        if outcome.retry or outcome.reject:
            return outcome
        return None

    def _json_objects(self, batch: Sequence[OutgoingRecord], outcome: SendOutcome) -> list[_Object]:
        """Objects of JSON lines bounded by total_file_size, in the batch's order."""
        objects: list[tuple[list[int], list[bytes]]] = []
        size = 0
        for i, record in enumerate(batch):
            try:
                line = self._line(record)
            except (_Unsendable, MalformedRecord) as exc:
                outcome.reject[i] = str(exc)
                continue
            if not objects or size + len(line) > self._max_object_bytes:
                objects.append(([], []))
                size = 0
            objects[-1][0].append(i)
            objects[-1][1].append(line)
            size += len(line)
        return [(indexes, b"".join(lines), "") for indexes, lines in objects]

    def _parquet_objects(self, batch: Sequence[OutgoingRecord], outcome: SendOutcome) -> list[_Object]:
        """One Parquet object per measurement (the records' ``name``), in the order they first appear;
        more when its records' JSON is over total_file_size."""
        groups: dict[str, list[list[tuple[int, dict[str, Any]]]]] = {}
        sizes: dict[str, int] = {}
        for i, record in enumerate(batch):
            name = str(record.data.get("name", ""))
            chunks = groups.setdefault(name, [[]])
            size = len(record.to_json())
            if chunks[-1] and sizes[name] + size > self._max_object_bytes:
                chunks.append([])
                sizes[name] = 0
            chunks[-1].append((i, record.data))
            sizes[name] = sizes.get(name, 0) + size
        objects: list[_Object] = []
        for name, chunks in groups.items():
            schema = self._schemas.of(name)
            for chunk in chunks:
                encoded = parquet.encode(chunk, schema, outcome.reject.__setitem__)
                if encoded is not None:
                    objects.append((encoded[0], encoded[1], name))
        return objects

    def _line(self, record: OutgoingRecord) -> bytes:
        p = self.params
        if p.log_key:
            if p.log_key not in record.data:
                raise _Unsendable(f"no key {p.log_key!r} (log_key) in the record")
            value = record.data[p.log_key]
            text = value if isinstance(value, str) else dump_record(value)
            text = text.replace("\n", "\\n")  # one record per line, whatever the value holds
        else:
            text = record.to_json()
        try:
            return (text + "\n").encode("utf-8")
        except UnicodeEncodeError as exc:
            raise _Unsendable(f"the record is not valid UTF-8 text: {exc}") from None

    def object_key(self, first: OutgoingRecord, index: int = 0, name: str = "") -> str:
        """The key of the object whose first record is ``first``: the same for every attempt."""
        p = self.params
        uuid = hashlib.sha256(first.record_id.encode("utf-8")).hexdigest()[:16]
        seconds = first.stamp_ns // 1_000_000_000
        # strftime first, so that a '%' in the tag stays as it is.
        key = expand_time(p.s3_key_format, seconds)
        key = _TAG_PART.sub(lambda m: self._tag_parts[int(m.group(1))], key)
        key = key.replace("$TAG", self.context.name).replace("$UUID", uuid).replace("$INDEX", str(index))
        key = key.replace("$NAME", _key_part(name))
        if "$UUID" not in p.s3_key_format and not p.static_file_path:
            key += f"-{uuid}"
        if p.parquet and not key.endswith(".parquet"):
            key += ".parquet"
        elif p.compression == "gzip" and not key.endswith(".gz"):
            key += ".gz"
        # An S3 key has no leading slash: "/fluent-bit-logs/…" would make an empty first folder.
        return key.lstrip("/")

    def _upload(self, key: str, data: bytes, metadata: dict[str, str]) -> None:
        p = self.params
        content_type = p.content_type or ("application/vnd.apache.parquet" if p.parquet else "application/x-ndjson")
        extra: dict[str, Any] = {"ContentType": content_type, "Metadata": metadata}
        if p.compression == "gzip" and not p.parquet:
            # mtime=0: the same records give the same bytes on every attempt.
            data = gzip.compress(data, mtime=0)
            extra["ContentEncoding"] = "gzip"
        if p.canned_acl:
            extra["ACL"] = p.canned_acl
        if p.storage_class:
            extra["StorageClass"] = p.storage_class
        try:
            if p.use_put_object or len(data) <= self._chunk_bytes:
                self._client.put_object(Bucket=p.bucket, Key=key, Body=data, **extra, **self._md5(data))
            else:
                self._multipart(key, data, extra)
        except (BotoCoreError, ClientError) as exc:
            message = self._describe(exc, key)
            self._problem(message)
            fix = _fix_for(exc)
            if fix:
                raise ConfigurationProblem(message, fix=fix) from None
            raise RetryableError(message) from None
        self._works_again("objects written")

    def _multipart(self, key: str, data: bytes, extra: dict[str, Any]) -> None:
        p = self.params
        # Parts no smaller than upload_chunk_size, more of them only up to S3's 10000.
        part_size = max(self._chunk_bytes, -(-len(data) // MAX_PARTS))
        upload_id = self._client.create_multipart_upload(Bucket=p.bucket, Key=key, **extra)["UploadId"]
        try:
            parts = []
            for number, start in enumerate(range(0, len(data), part_size), start=1):
                body = data[start : start + part_size]
                answer = self._client.upload_part(
                    Bucket=p.bucket, Key=key, UploadId=upload_id, PartNumber=number, Body=body, **self._md5(body)
                )
                parts.append({"PartNumber": number, "ETag": answer["ETag"]})
            self._client.complete_multipart_upload(
                Bucket=p.bucket, Key=key, UploadId=upload_id, MultipartUpload={"Parts": parts}
            )
        except BaseException:
            # The parts already stored would be billed until a lifecycle rule removes them.
            # An unreachable store cannot abort either: the failure being raised says so.
            with contextlib.suppress(BotoCoreError, ClientError):
                self._client.abort_multipart_upload(Bucket=p.bucket, Key=key, UploadId=upload_id)
            raise

    def _md5(self, body: bytes) -> dict[str, str]:
        if not self.params.send_content_md5:
            return {}
        return {"ContentMD5": base64.b64encode(hashlib.md5(body).digest()).decode("ascii")}

    # -- messages ----------------------------------------------------------------------------------
    def _describe(self, exc: Exception, key: str) -> str:
        """What to tell the operator about a failed upload (every failure is retried)."""
        common = self.params.common_failure(exc, "S3", self.where)
        if common is not None:
            return common
        if isinstance(exc, ClientError):
            error = exc.response.get("Error", {})
            code, text = str(error.get("Code", "")), str(error.get("Message", ""))
            status = exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0)
            if code == "NoSuchBucket":
                return self.params.scrub(
                    f"no {self.where}: create it or correct `bucket` / `region` / `endpoint` ({text})"
                )
            if code in S3_CREDENTIAL_CODES:
                return self.params.scrub(
                    f"S3 refused the credentials for {self.where}: {code}: {text} "
                    "(check the access key, secret key, role_arn and the policy's s3:PutObject)"
                )
            return self.params.scrub(f"cannot write {key} to {self.where}: {code or status}: {text}")
        return self.params.scrub(f"cannot write {key} to {self.where}: {type(exc).__name__}: {exc}")


def _fix_for(exc: Exception) -> str:
    """What to check when a failed upload is one retrying alone does not mend (dc_destinations.health)."""
    if isinstance(exc, CREDENTIALS_MISSING):
        return "give credentials: access_key_id and secret_access_key, or boto3's default chain"
    if not isinstance(exc, ClientError):
        return ""
    code = str(exc.response.get("Error", {}).get("Code", ""))
    if code == "NoSuchBucket":
        return "create the bucket, or correct bucket / region / endpoint"
    if code in S3_CREDENTIAL_CODES:
        return "check the access key, secret key, role_arn and the policy's s3:PutObject"
    return ""
