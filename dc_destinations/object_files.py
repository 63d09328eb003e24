"""Files named in records, as objects of an S3-compatible store: which file goes to which key, and
whether the store holds it intact.

Shared by the destinations that deal with files rather than records: MinIO (it uploads them) and
FilesMetrics (it tracks them and deletes them once every storage has them). A record names its
files by dotted paths (``src_fields``: ``local_paths.pgm``) and their object keys the same way
(``upload_fields``: ``remote_paths.minio.pgm``), as the original's Go plugins did.

"Intact" means the stored object has the local file's size and checksum. S3 reports the checksum
as the object's ETag: the MD5 of the content for a single upload, or for a multipart upload the MD5
of the parts' MD5 digests followed by ``-<number of parts>`` — which depends on the part size, so
DC's uploader records it in the object's metadata (``x-amz-meta-dc-part-size``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import re
import urllib.parse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NoReturn, Protocol, TypeVar

from dc_core.confined_files import (
    Confinement,
    ConfinementParams,
    FileRefused,
    OpenedFile,
    confinement_of,
)
from dc_core.destination import OutgoingRecord, ProbeResult, RetryableError
from dc_core.errors import ConfigError
from dc_core.logs import BurstLog, Logger
from dc_core.params import param
from dc_destinations.aws import (
    CREDENTIALS_MISSING,
    S3_CREDENTIAL_CODES,
    BotoCoreError,
    ClientError,
    aws_session,
    bucket_problem,
    check_credentials,
    endpoint_url,
    make_client,
    region_problem,
    warn_if_signed_in_clear,
)
from dc_destinations.record_fields import field_value

PART_SIZE_METADATA = "dc-part-size"
"""Metadata key (``x-amz-meta-dc-part-size``) holding the part size of a multipart upload."""
RECORD_ID_METADATA = "dc-record-id"
ROBOT_NAME_METADATA = "dc-robot-name"
RUN_ID_METADATA = "dc-run-id"
RECORD_COUNT_METADATA = "dc-record-count"
# What a metadata value keeps as it is: printable ASCII but "%", which percent-encodes the rest
# (an HTTP header carries no other byte reliably).
_METADATA_SAFE = "".join(chr(c) for c in range(0x20, 0x7F) if chr(c) not in "%")

_MIB = 1024 * 1024
_READ_CHUNK = _MIB
_ETAG = re.compile(r"[0-9a-f]{32}(-(\d+))?")
_BUSY_CODES = frozenset({"SlowDown", "Throttling", "ThrottlingException", "RequestTimeout", "RequestTimeTooSkewed"})
_ABSENT_CODES = frozenset({"404", "NoSuchKey", "NotFound"})
# Part sizes other tools use, tried first when an object's ETag has parts of an unknown size.
_USUAL_PART_SIZES = (8 * _MIB, 16 * _MIB, 5 * _MIB, 64 * _MIB, 32 * _MIB, 128 * _MIB)
_MOST_CANDIDATES = 6


@dataclass(frozen=True, kw_only=True, repr=False)
class ObjectStoreParams:
    """One storage of files: the original's ``minio.*`` / ``s3.*`` keys."""

    endpoint: str = param(
        "127.0.0.1:9000",
        doc="Store address: host:port (http or https by use_ssl) or a URL; empty: AWS's endpoint of region",
    )
    access_key_id: str = param("", doc="Access key ID; empty: boto3's default chain (env, profile, instance role)")
    secret_access_key: str = param("", secret=True, doc="Secret access key with access_key_id (never logged)")
    use_ssl: bool = param(True, doc="HTTPS to an endpoint given without a scheme (false: plain HTTP)")
    bucket: str = param(
        "dc-bucket",
        check=bucket_problem,
        doc='Bucket of the objects (the original\'s default "dc_bucket" is not a valid bucket name)',
    )
    region: str = param("us-east-1", check=region_problem, doc="Region of the bucket (signs the requests)")
    src_fields: list[str] = param([], doc="Dotted paths to the local file paths in a record (local_paths.pgm)")
    upload_fields: list[str] = param(
        [], doc="Dotted paths to the object keys, one per src_fields entry (remote_paths.minio.pgm)"
    )

    def __post_init__(self) -> None:
        try:
            check_credentials(self.access_key_id, self.secret_access_key, "", "", "")
        except ConfigError as exc:  # aws.py names the S3 destination's keys: name these
            path = "secret_access_key" if self.access_key_id else "access_key_id"
            raise ConfigError(path, "set access_key_id and secret_access_key together (or neither)") from exc
        for name in ("src_fields", "upload_fields"):
            for i, dotted in enumerate(getattr(self, name)):
                if not dotted.strip("."):
                    raise ConfigError(
                        f"{name}[{i}]", f'expected a dotted path such as "local_paths.pgm", got "{dotted}"'
                    )
        if len(self.src_fields) != len(self.upload_fields):
            raise ConfigError(
                "upload_fields",
                f"expected one entry per src_fields entry: {len(self.upload_fields)} upload_fields "
                f"for {len(self.src_fields)} src_fields",
            )

    def __repr__(self) -> str:
        shown = (f for f in dataclasses.fields(self) if not f.metadata.get("secret"))
        return f"{type(self).__name__}({', '.join(f'{f.name}={getattr(self, f.name)!r}' for f in shown)})"

    def url(self) -> str | None:
        """The store's URL: ``endpoint`` as a URL as it is, host:port with the scheme ``use_ssl`` says."""
        return endpoint_url(self.endpoint, self.use_ssl)

    def _warn_if_in_clear(self, logger: Logger, destination: str) -> bool:
        """The shared warning (:func:`dc_destinations.aws.warn_if_signed_in_clear`) for a store over plain HTTP."""
        key = self.access_key_id or "(boto3's chain)"
        return warn_if_signed_in_clear(
            logger,
            destination,
            self.url(),
            signed=f"requests signed with access key {key} and the files",
            fix="use an https endpoint (use_ssl: true, or an https:// URL)",
        )

    def client(self, logger: Logger, destination: str, timeout: float = 30.0) -> Any:
        """A boto3 S3 client of the storage for ``destination``, after the warning about a store in
        clear; making it reads configuration only, nothing is sent."""
        self._warn_if_in_clear(logger, destination)
        url = self.url()
        session = aws_session(
            name=destination,
            region=self.region,
            access_key=self.access_key_id,
            secret_key=self.secret_access_key,
            timeout=timeout,
        )
        return make_client(
            "s3",
            session=session,
            region=self.region,
            endpoint=url,
            timeout=timeout,
            # One immediate retry of a failed request; the destination server's backoff does the rest.
            attempts=2,
            # MinIO, SeaweedFS and Ceph rarely resolve bucket.host names: path-style unless it is AWS.
            addressing_style="path" if url and ".amazonaws.com" not in url else "auto",
        )


# -- where the files are named ---------------------------------------------------------------------


@dataclass(frozen=True)
class FilePair:
    """One file of a record and the object it goes to.

    ``local_path`` is empty when the value at ``src_field`` is not a path (a number, an object);
    ``key`` is None when the record has no usable key at ``upload_field``.
    """

    src_field: str
    upload_field: str
    local_path: str
    key: str | None


def file_pairs(data: Mapping[str, Any], params: ObjectStoreParams) -> list[FilePair]:
    """The record's files, in ``src_fields`` order; a src field the record lacks names no file."""
    pairs = []
    for src_field, upload_field in zip(params.src_fields, params.upload_fields, strict=True):
        local = field_value(data, src_field)
        if local is None:
            continue
        key = field_value(data, upload_field)
        # An S3 key has no leading slash: "/robot/…" would make an empty first folder. One is
        # removed (the original's records had one); what is left is checked by the destination.
        key_text = key.removeprefix("/") if isinstance(key, str) else ""
        pairs.append(FilePair(src_field, upload_field, local if isinstance(local, str) else "", key_text or None))
    return pairs


def record_metadata(records: Sequence[OutgoingRecord]) -> dict[str, str]:
    """User metadata pointing an object back at the records it came from (``x-amz-meta-dc-*``): the
    first record's ``record_id``, and the robot and run when every record names the same one; with
    more than one record, their number. Values outside printable ASCII are percent-encoded (UTF-8)."""
    metadata = {RECORD_ID_METADATA: records[0].record_id}
    for key, meta in (("robot_name", ROBOT_NAME_METADATA), ("run_id", RUN_ID_METADATA)):
        values = {field_value(record.data, key) for record in records}
        (value,) = values if len(values) == 1 else (None,)
        if isinstance(value, (str, int)) and not isinstance(value, bool) and str(value):
            metadata[meta] = str(value)
    if len(records) > 1:
        metadata[RECORD_COUNT_METADATA] = str(len(records))
    return {key: urllib.parse.quote(value, safe=_METADATA_SAFE) for key, value in metadata.items()}


class _Closable(Protocol):
    def close(self) -> None: ...


HeldT = TypeVar("HeldT", bound=_Closable)
ResultT = TypeVar("ResultT")


class RecordFiles:
    """The files records name, as the destinations that deal with files (MinIO, FilesMetrics) take
    them: through the confinement, refusals counted and logged per burst, and whatever a batch
    opened closed when the batch ends."""

    def __init__(self, context: Any) -> None:
        self.confinement: Confinement | None = None
        self.refused = 0
        self._refused_log = BurstLog(
            context.logger.warning, f"destination {context.name}: files or keys named by records refused"
        )

    def configure(self, params: ConfinementParams) -> Confinement:
        self.confinement = confinement_of(params)
        return self.confinement

    def batch(self, send: Callable[[list[HeldT]], ResultT]) -> ResultT:
        """``send(held)``; what it puts in ``held`` (it holds opened files) is closed however it ends."""
        self._refused_log.tick()
        held: list[HeldT] = []
        try:
            return send(held)
        finally:
            for item in held:
                item.close()

    def open(
        self, pair: FilePair, problems: list[str], opened: OpenedFile | None = None
    ) -> tuple[bool, OpenedFile | None]:
        """Check the pair's key and open its file (``opened``: the same file, opened already); the file
        is None when there is none. (False, None) with the reason added to ``problems`` when the pair
        names no key or no path, the key or the file is refused, or the file cannot be read."""
        assert self.confinement is not None, "open() before configure()"
        if pair.key is None:
            problems.append(f"no object key at {pair.upload_field} for {pair.local_path or pair.src_field}")
            return False, None
        if not pair.local_path:
            problems.append(f"{pair.src_field} holds no file path")
            return False, None
        try:
            self.confinement.check_key(pair.key)
            return True, opened if opened is not None else self.confinement.open(pair.local_path)
        except FileRefused as exc:
            self.refused += 1
            reason = f"refused: {exc} ({pair.src_field})"
            self._refused_log.event(1, reason)
            problems.append(reason)
        except OSError as exc:
            problems.append(f"cannot read {pair.local_path} ({pair.src_field}): {exc.strerror or exc}")
        return False, None


# -- checksums ---------------------------------------------------------------------------------------


class _PartHasher:
    """MD5 digests of a content's consecutive parts (one part when ``part_size`` is None), fed in chunks."""

    def __init__(self, part_size: int | None) -> None:
        self.part_size = part_size
        self.digests: list[bytes] = []
        self._part = hashlib.md5(usedforsecurity=False)
        self._in_part = 0

    def update(self, chunk: bytes) -> None:
        view = memoryview(chunk)
        while view:
            take = len(view) if self.part_size is None else min(len(view), self.part_size - self._in_part)
            self._part.update(view[:take])
            self._in_part += take
            view = view[take:]
            if self._in_part == self.part_size:
                self.digests.append(self._part.digest())
                self._part = hashlib.md5(usedforsecurity=False)
                self._in_part = 0

    def finish(self) -> list[bytes]:
        if self._in_part or not self.digests:
            self.digests.append(self._part.digest())
            self._in_part = 0
        return self.digests

    def etag(self) -> str:
        digests = self.finish()
        if self.part_size is None:
            return digests[0].hex()
        return f"{hashlib.md5(b''.join(digests), usedforsecurity=False).hexdigest()}-{len(digests)}"


@dataclass(frozen=True)
class NoLocalFile:
    """A file a record names that is not there: only the store can tell about it."""

    path: str


LocalFile = str | OpenedFile
"""A local file by path, or opened by :class:`dc_core.confined_files.Confinement` (read through its
descriptor, whatever its path names meanwhile)."""


def _name(local: LocalFile | NoLocalFile) -> str:
    return local if isinstance(local, str) else local.path


def _hash_file(local: LocalFile, hashers: Sequence[_PartHasher]) -> None:
    if isinstance(local, OpenedFile):
        for chunk in local.reader():
            for hasher in hashers:
                hasher.update(chunk)
        return
    with open(local, "rb") as f:
        while chunk := f.read(_READ_CHUNK):
            for hasher in hashers:
                hasher.update(chunk)


def local_etag(local: LocalFile, part_size: int | None) -> str:
    """The ETag S3 gives this file's content: uploaded in one request (``part_size`` None) or in parts."""
    hasher = _PartHasher(part_size)
    _hash_file(local, [hasher])
    return hasher.etag()


def part_digests(local: LocalFile, part_size: int | None) -> list[bytes]:
    """MD5 digest of each part of the file (of the whole file when ``part_size`` is None)."""
    hasher = _PartHasher(part_size)
    _hash_file(local, [hasher])
    return hasher.finish()


def _implied_part_sizes(size: int, parts: int) -> list[int]:
    """Part sizes that cut ``size`` bytes into ``parts`` parts, the likeliest first (at most a few)."""
    if parts <= 1:
        return [max(size, 1)]  # any part size from the content's size up gives the same ETag
    smallest = -(-size // parts)
    largest = -(-size // (parts - 1)) - 1
    if smallest > largest:
        return []
    whole_mib = range(-(-smallest // _MIB), largest // _MIB + 1)
    usual = [s for s in _USUAL_PART_SIZES if smallest <= s <= largest]
    candidates = [*usual, *(m * _MIB for m in whole_mib if m * _MIB not in usual), smallest]
    return list(dict.fromkeys(candidates))[:_MOST_CANDIDATES]


# -- the store's answers -----------------------------------------------------------------------------


@dataclass(frozen=True)
class StoreFailure:
    """What a failed request means: ``whole_store`` failures stop a batch, the others concern one object."""

    kind: str  # "network", "credentials", "no-bucket", "busy" or "object": one log line per kind
    message: str
    whole_store: bool


# What to check when the store's failure is one retrying alone does not mend (dc_destinations.health).
_FIXES = {
    "credentials": "check access_key_id and secret_access_key (or boto3's credential chain) and the bucket's policy",
    "no-bucket": "create the bucket, or correct bucket / endpoint",
}


class StoreUnavailable(RetryableError):
    """The store cannot take or show anything now (unreachable, refused credentials, no bucket).

    ``fix`` is set for refused credentials and a missing bucket: the destination is then reported
    failing at once (dc_core.destination.ConfigurationProblem's meaning).
    """

    def __init__(self, failure: StoreFailure) -> None:
        super().__init__(failure.message)
        self.failure = failure
        self.fix = _FIXES.get(failure.kind, "")


def store_where(bucket: str, client: Any) -> str:
    """'bucket <name> at <endpoint>': named in every message, so an operator sees what to fix."""
    return f"bucket {bucket} at {client.meta.endpoint_url}"


def store_failure(exc: Exception, where: str, doing: str) -> StoreFailure:
    """What to tell the operator about ``exc``, raised while ``doing`` something in ``where``."""
    if isinstance(exc, ClientError):
        error = exc.response.get("Error", {})
        code, text = str(error.get("Code", "")), str(error.get("Message", ""))
        status = int(exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0) or 0)
        if code in S3_CREDENTIAL_CODES or status == 403:
            return StoreFailure(
                "credentials",
                f"the store refused the credentials for {where}: {code or status}: {text} "
                "(check access_key_id, secret_access_key and the bucket's policy)",
                whole_store=True,
            )
        if code == "NoSuchBucket":
            return StoreFailure(
                "no-bucket", f"no {where}: create it (create_bucket) or correct bucket / endpoint", whole_store=True
            )
        if code in _BUSY_CODES or status >= 500:
            return StoreFailure("busy", f"the store of {where} cannot {doing} now: {code or status}: {text}", True)
        return StoreFailure("object", f"cannot {doing} in {where}: {code or status}: {text}", whole_store=False)
    if isinstance(exc, CREDENTIALS_MISSING):
        return StoreFailure(
            "credentials",
            f"no credentials for {where}: set access_key_id and secret_access_key, or give them to boto3's "
            "default chain (AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, a profile, an instance role)",
            whole_store=True,
        )
    return StoreFailure("network", f"cannot reach {where}: {exc}", whole_store=True)


def probe_bucket(client: Any, bucket: str, where: str) -> ProbeResult:
    """HEAD of the bucket with the real credentials (``dc check``): it exists and they may see it.
    A HEAD answer has no body, hence no error code but its status."""
    try:
        client.head_bucket(Bucket=bucket)
    except (BotoCoreError, ClientError) as exc:
        error = getattr(exc, "response", {}).get("Error", {})
        if str(error.get("Code", "")) in ("404", "NoSuchBucket"):
            return ProbeResult(False, f"no {where}", "create the bucket (create_bucket), or correct bucket / endpoint")
        failure = store_failure(exc, where, "read the bucket")
        fixes = {"credentials": "check access_key_id and secret_access_key", "network": "check endpoint and use_ssl"}
        return ProbeResult(False, failure.message, fixes.get(failure.kind, ""))
    return ProbeResult(True, f"{where} exists, credentials accepted")


def stored_object(client: Any, bucket: str, key: str) -> dict[str, Any] | None:
    """The object's HEAD answer, None when there is no such object; :class:`StoreUnavailable` (or
    :class:`RetryableError` about this object) when the store cannot say."""
    try:
        head: dict[str, Any] = client.head_object(Bucket=bucket, Key=key)
    except ClientError as exc:
        if str(exc.response.get("Error", {}).get("Code", "")) in _ABSENT_CODES:
            return None
        _raise_failure(exc, store_where(bucket, client), f"look up {key}")
    except BotoCoreError as exc:
        _raise_failure(exc, store_where(bucket, client), f"look up {key}")
    return head


def _raise_failure(exc: Exception, where: str, doing: str) -> NoReturn:
    failure = store_failure(exc, where, doing)
    if failure.whole_store:
        raise StoreUnavailable(failure) from None
    raise RetryableError(failure.message) from None


@dataclass(frozen=True)
class Verification:
    """Whether the store holds ``key`` as the local file is; ``size`` and ``etag`` are the object's."""

    verified: bool
    reason: str
    size: int | None
    etag: str


def verify_stored(client: Any, bucket: str, key: str, local: LocalFile | NoLocalFile) -> Verification:
    """Compare the stored object with the local file: size, then ETag (see the module documentation).

    A local file that is gone cannot be compared: the object counts as verified when it exists
    (an earlier upload verified it before the file was deleted). Raises :class:`StoreUnavailable`
    when the store cannot be asked, :class:`RetryableError` when it cannot answer about this object.
    """
    head = stored_object(client, bucket, key)
    if head is None:
        return Verification(False, f"no object {key}", None, "")
    size = int(head.get("ContentLength", -1))
    etag = str(head.get("ETag", "")).strip('"')
    local_path = _name(local)
    try:
        if isinstance(local, NoLocalFile):
            raise FileNotFoundError(local_path)
        local_size = os.fstat(local.fd).st_size if isinstance(local, OpenedFile) else os.stat(local).st_size
    except FileNotFoundError:
        return Verification(True, f"{key} is stored; {local_path} is gone, so its content is not compared", size, etag)
    if size != local_size:
        return Verification(False, f"{key} holds {size} bytes, {local_path} {local_size}", size, etag)
    match = _ETAG.fullmatch(etag)
    if match is None:
        return Verification(
            True, f"{key} has the file's size; its ETag {etag!r} is not an MD5, not compared", size, etag
        )
    guessed = False
    candidates: list[int | None] = [None]
    if match.group(2) is not None:
        recorded = str(head.get("Metadata", {}).get(PART_SIZE_METADATA, ""))
        if recorded.isdigit() and int(recorded) > 0:
            candidates = [int(recorded)]
        else:  # uploaded by another tool: the part sizes that give this many parts
            guessed = True
            candidates = list(_implied_part_sizes(size, int(match.group(2))))
    if not candidates:
        return Verification(True, f"{key} has the file's size; parts of unknown size, ETag not compared", size, etag)
    hashers = [_PartHasher(part_size) for part_size in candidates]
    _hash_file(local, hashers)
    local_etags = [hasher.etag() for hasher in hashers]
    if etag in local_etags:
        return Verification(True, f"{key} matches {local_path}: {size} bytes, ETag {etag}", size, etag)
    if guessed:
        return Verification(
            False, f"{key} has the file's size, not its ETag with the likely part sizes ({etag})", size, etag
        )
    return Verification(False, f"{key} differs from {local_path}: ETag {etag}, the file's {local_etags[0]}", size, etag)
