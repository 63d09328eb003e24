"""MinIO destination: the files records name, uploaded to MinIO, S3 or another S3-compatible store, and verified.

A record of a file-saving measurement (Map, Camera) carries the paths of its files and the object
key each one goes to (``src_fields`` / ``upload_fields``). A record is confirmed only once every
file it names is stored and verified — the object's size and ETag compared with the local file's —
so the buffer keeps the record, and retries it, until the store really has the files. A retried
record costs a HEAD request per file: files already stored intact are not sent again.

Files above ``multipart_threshold`` go in parts. An interrupted multipart upload is resumed by the
next attempt: the parts the store already holds with the right content (their ETag is their MD5)
are kept, the others sent. Nothing is aborted because the network failed, which is what makes it
resumable.

A file must be left unmodified for ``complete_after`` seconds before it is taken as complete. Files
younger than that are looked at again after one wait per batch (at most ``complete_after``,
overlapping the batch's other uploads): unchanged, they go; still growing, their record is retried
later. A file that is missing is looked for again after the same wait (DC's own measurements write
their files just after publishing the record), then its record goes to the dead letters with the
path — unless the object is stored already (a retry after ``delete_when_sent`` deleted it).
"""

from __future__ import annotations

import base64
import contextlib
import functools
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NoReturn

from dc_core.confined_files import ConfinementParams, OpenedFile, delete_opened
from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import compat_param, param
from dc_destinations.aws import (
    MAX_PART_BYTES,
    MAX_PARTS,
    MAX_PUT_BYTES,
    MIN_PART_BYTES,
    BotoCoreError,
    ClientError,
    size_problem,
)
from dc_destinations.content_types import content_type as file_content_type
from dc_destinations.object_files import (
    PART_SIZE_METADATA,
    FilePair,
    ObjectStoreParams,
    RecordFiles,
    StoreUnavailable,
    file_pairs,
    part_digests,
    probe_bucket,
    record_metadata,
    store_failure,
    store_where,
    stored_object,
    verify_stored,
)
from dc_destinations.settings import parse_size

_ALREADY_THERE = ("BucketAlreadyOwnedByYou", "BucketAlreadyExists")
_NO_BUCKET = ("404", "NoSuchBucket", "NotFound")


@dataclass(frozen=True, kw_only=True, repr=False)
class MinIOParams(ObjectStoreParams, ConfinementParams):
    create_bucket: bool = param(True, doc="Create the bucket at the first upload if it does not exist")
    multipart_threshold: str = param(
        "64M", check=size_problem, doc="Files larger than this are uploaded in parts, resumably (at most 5G)"
    )
    part_size: str = param("16M", check=size_problem, doc="Size of the parts of a multipart upload (5M to 5G)")
    complete_after: float = param(
        1.0, minimum=0.0, maximum=60.0, doc="Seconds a file must be left unmodified before it is uploaded"
    )
    delete_when_sent: bool = param(
        False, doc="Delete each local file once its object is verified (one storage; FilesMetrics for several)"
    )
    timeout: float = param(30.0, minimum=0.1, maximum=3600, doc="Seconds to connect and for each read")
    verbose_plugin: bool = compat_param(False, "DC logs at dc-bringup's --log-level (there is no Go plugin)")
    plugin_path: str = compat_param("", "there is no Go plugin to load")

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.src_fields:
            raise ConfigError("src_fields", 'expected at least one dotted path to a file, such as "local_paths.pgm"')
        part = parse_size(self.part_size) or 0
        if not MIN_PART_BYTES <= part <= MAX_PART_BYTES:
            raise ConfigError("part_size", f'expected 5M to 5G (S3\'s part sizes), got "{self.part_size}"')
        if (parse_size(self.multipart_threshold) or 0) > MAX_PUT_BYTES:
            raise ConfigError(
                "multipart_threshold",
                f'expected at most 5G (S3\'s largest single upload), got "{self.multipart_threshold}"',
            )


@dataclass
class _File:
    pair: FilePair
    opened: OpenedFile | None  # checked and open (confined_files); None: there was no file
    ready: bool = False  # complete, or gone with its object stored
    gone_but_stored: bool = False

    @property
    def seen(self) -> os.stat_result | None:
        return self.opened.status if self.opened is not None else None

    @property
    def path(self) -> str:
        return self.pair.local_path

    @property
    def key(self) -> str:
        assert self.pair.key is not None
        return self.pair.key


@dataclass
class _Record:
    index: int
    files: list[_File] = field(default_factory=list)
    rejects: list[str] = field(default_factory=list)  # dead letter, once nothing is left to retry
    metadata: dict[str, str] = field(default_factory=dict)  # x-amz-meta-dc-* of the record's objects
    retries: list[str] = field(default_factory=list)

    @property
    def waiting(self) -> bool:
        return any(not f.ready for f in self.files)

    def close(self) -> None:
        for file in self.files:
            if file.opened is not None:
                file.opened.close()


class MinIO(Destination[MinIOParams]):
    """Upload the files records name to MinIO or S3, verify them, and optionally delete them locally."""

    def __init__(self, context: Any, params: MinIOParams) -> None:
        super().__init__(context, params)
        self._client: Any = None
        self._bucket_ready = False
        self._last_problem = ""
        self._part_bytes = parse_size(params.part_size) or MIN_PART_BYTES
        self._threshold = parse_size(params.multipart_threshold) or MAX_PUT_BYTES
        self._counts = dict.fromkeys(
            (
                "files_uploaded",
                "bytes_uploaded",
                "files_already_stored",
                "parts_reused",
                "verification_failures",
                "files_missing",
                "files_deleted",
                "delete_failures",
            ),
            0,
        )
        self.where = ""
        self._files = RecordFiles(context)

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        # Creating a client reads the configuration and credentials chain only: nothing is sent yet.
        self._files.configure(self.params)
        self._client = self.params.client(self.context.logger, self.context.name, self.params.timeout)
        self.where = store_where(self.params.bucket, self._client)

    def probe(self) -> ProbeResult:
        return probe_bucket(self._client, self.params.bucket, self.where)

    def on_activate(self) -> None:
        # The store is not probed here: an unreachable store must not hold up activation, and the
        # first batch says clearly what is wrong.
        fields = ", ".join(self.params.src_fields)
        assert self._files.confinement is not None
        self.context.logger.info(
            f"uploading the files of {fields} to {self.where}, from {self._files.confinement.describe()} only"
        )

    def on_cleanup(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def file_fields(self) -> list[str]:
        return list(self.params.src_fields)  # a record is confirmed once its objects are verified

    def counters(self) -> dict[str, int]:
        return {**self._counts, "files_refused": self._files.refused}

    def _pause(self, seconds: float) -> bool:
        """Wait for files to be complete; True when interrupted (the destination is stopping)."""
        return self.stopping.wait(seconds)

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        return self._files.batch(functools.partial(self._send, batch))

    def _send(self, batch: Sequence[OutgoingRecord], records: list[_Record]) -> SendOutcome | None:
        outcome = SendOutcome()
        confirmed: set[int] = set()
        try:
            self._ensure_bucket()
            looked_at = time.monotonic()
            records.extend(self._look(i, outgoing) for i, outgoing in enumerate(batch))
            for record in records:
                if not record.waiting:
                    self._deliver(record, outcome, confirmed)
            waiting = [record for record in records if record.waiting]
            if waiting:
                interrupted = self._pause(self._wait_needed(waiting, looked_at))
                for record in waiting:
                    self._look_again(record, interrupted)
                    self._deliver(record, outcome, confirmed)
        except StoreUnavailable as exc:
            message = self._scrub(str(exc))
            self._problem(exc.failure.kind, message)
            if not confirmed and not outcome.retry and not outcome.reject:
                raise RetryableError(message) from None  # nothing of the batch went: the whole batch is retried
            decided = confirmed | set(outcome.retry) | set(outcome.reject)
            outcome.retry.update((i, message) for i in range(len(batch)) if i not in decided)
            return outcome
        if self._last_problem:
            self.context.logger.info(f"{self.where}: reachable again")
            self._last_problem = ""
        return outcome if outcome.retry or outcome.reject else None

    def _ensure_bucket(self) -> None:
        if self._bucket_ready or not self.params.create_bucket:
            return
        bucket = self.params.bucket
        try:
            self._client.head_bucket(Bucket=bucket)
        except ClientError as exc:
            if str(exc.response.get("Error", {}).get("Code", "")) in _NO_BUCKET:
                self._create_bucket()
            elif store_failure(exc, self.where, "").kind != "credentials":
                self._fail(exc, "look up the bucket")
            # else: looking at a bucket needs s3:ListBucket, which an uploader may lack; if the
            # credentials are wrong, the first object says so.
        except BotoCoreError as exc:
            self._fail(exc, "look up the bucket")
        self._bucket_ready = True

    def _create_bucket(self) -> None:
        request: dict[str, Any] = {"Bucket": self.params.bucket}
        if self.params.region != "us-east-1":  # S3 refuses the default region spelled out
            request["CreateBucketConfiguration"] = {"LocationConstraint": self.params.region}
        try:
            self._client.create_bucket(**request)
        except ClientError as exc:
            if str(exc.response.get("Error", {}).get("Code", "")) not in _ALREADY_THERE:
                self._fail(exc, "create the bucket")
            return
        except BotoCoreError as exc:
            self._fail(exc, "create the bucket")
        self.context.logger.info(f"created {self.where}")

    def _open(self, pair: FilePair, record: _Record) -> tuple[bool, OpenedFile | None]:
        """The pair's file opened if it passes the checks (confined_files); (False, None) when refused or unreadable."""
        return self._files.open(pair, record.rejects)

    def _look(self, index: int, record: OutgoingRecord) -> _Record:
        """The record's files as they are now; a missing file is looked up in the store."""
        looked = _Record(index, metadata=record_metadata([record]))
        for pair in file_pairs(record.data, self.params):
            usable, opened = self._open(pair, looked)
            if not usable:
                continue
            file = _File(pair, opened)
            looked.files.append(file)
            seen = file.seen
            if seen is None:
                file.ready = file.gone_but_stored = (
                    stored_object(self._client, self.params.bucket, file.key) is not None
                )
            else:
                file.ready = _age(seen) >= self.params.complete_after
        return looked

    def _wait_needed(self, waiting: list[_Record], looked_at: float) -> float:
        """Until the youngest file is complete_after old (a missing one: complete_after after the first look)."""
        limit = self.params.complete_after
        since_look = time.monotonic() - looked_at
        left = max(
            limit - (_age(f.seen) if f.seen is not None else since_look)
            for r in waiting
            for f in r.files
            if not f.ready
        )
        return max(0.0, min(limit, left))

    def _look_again(self, record: _Record, interrupted: bool) -> None:
        limit = self.params.complete_after
        for file in record.files:
            if file.ready:
                continue
            where = f"{file.path} ({file.pair.src_field})"
            before = file.seen
            usable, opened = self._open(file.pair, record)
            if not usable:
                continue
            if file.opened is not None:
                file.opened.close()
            file.opened = opened  # what is uploaded is what was opened now, and checked now
            now = opened.status if opened is not None else None
            unchanged = before is not None and now is not None and _same(before, now)
            if now is None and before is None:
                self._counts["files_missing"] += 1
                record.rejects.append(f"no file {where}")
            elif now is None:
                record.retries.append(f"{where} vanished while waiting for it to be complete")
            elif (unchanged and not interrupted) or _age(now) >= limit:
                file.ready = True
            elif interrupted:
                record.retries.append(f"{where} not uploaded: the destination is stopping")
            else:
                record.retries.append(f"{where} is still being written (modified {max(0.0, _age(now)):.1f} s ago)")

    def _deliver(self, record: _Record, outcome: SendOutcome, confirmed: set[int]) -> None:
        verified: dict[str, bool] = {}  # local path -> every object made from it verified
        opened: dict[str, OpenedFile] = {}
        for file in record.files:
            if not file.ready:
                continue
            try:
                ok = self._store(file, record.metadata)
            except StoreUnavailable:
                raise
            except RetryableError as exc:
                record.retries.append(str(exc))
                ok = False
            except FileNotFoundError:
                record.retries.append(f"{file.path} ({file.pair.src_field}) vanished during the upload")
                ok = False
            except OSError as exc:
                record.rejects.append(f"cannot read {file.path} ({file.pair.src_field}): {exc.strerror or exc}")
                ok = False
            verified[file.path] = verified.get(file.path, True) and ok
            if file.opened is not None:
                opened.setdefault(file.path, file.opened)
        if record.retries:
            outcome.retry[record.index] = self._scrub("; ".join(record.retries + record.rejects))
        elif record.rejects:
            outcome.reject[record.index] = self._scrub("; ".join(record.rejects))
        else:
            confirmed.add(record.index)
        if self.params.delete_when_sent:
            # Only files that passed the checks were opened: nothing else can be deleted.
            self._delete([opened[path] for path, ok in verified.items() if ok and path in opened])

    def _store(self, file: _File, metadata: dict[str, str]) -> bool:
        """Upload the file unless the store holds it intact already; True once verified."""
        if file.gone_but_stored:
            return True
        p = self.params
        assert file.opened is not None
        before = verify_stored(self._client, p.bucket, file.key, file.opened)
        if before.verified:
            self._counts["files_already_stored"] += 1
            return True
        size = self._upload(file.opened, file.key, metadata)
        after = verify_stored(self._client, p.bucket, file.key, file.opened)
        if not after.verified:
            self._counts["verification_failures"] += 1
            raise RetryableError(f"{file.key} not verified after the upload: {after.reason}")
        self._counts["files_uploaded"] += 1
        self._counts["bytes_uploaded"] += size
        return True

    def _upload(self, opened: OpenedFile, key: str, metadata: dict[str, str]) -> int:
        path = opened.path
        size = os.fstat(opened.fd).st_size
        content_type = file_content_type(path)
        try:
            if size <= self._threshold:
                self._paced(size, key)
                (digest,) = part_digests(opened, None)
                with _reopened(opened) as body:
                    self._client.put_object(
                        Bucket=self.params.bucket,
                        Key=key,
                        Body=body,
                        ContentType=content_type,
                        ContentMD5=_b64(digest),
                        Metadata=metadata,
                    )
            else:
                self._multipart(opened, key, size, content_type, metadata)
        except (BotoCoreError, ClientError) as exc:
            self._fail(exc, f"upload {key}")
        return size

    def _paced(self, nbytes: int, key: str) -> None:
        """Within the destination's caps (max_bytes_per_s, link): a part waits for its bytes' turn."""
        if not self.pace(nbytes):
            raise RetryableError(f"{key} not uploaded: the destination is stopping")

    def _multipart(self, opened: OpenedFile, key: str, size: int, content_type: str, metadata: dict[str, str]) -> None:
        p = self.params
        # Parts no smaller than part_size, larger only to stay within S3's 10000 parts.
        part_size = max(self._part_bytes, -(-size // MAX_PARTS))
        digests = part_digests(opened, part_size)
        upload_id, stored = self._resumable(key, size, part_size, digests)
        if upload_id is None:
            created = self._client.create_multipart_upload(
                Bucket=p.bucket,
                Key=key,
                ContentType=content_type,
                Metadata={**metadata, PART_SIZE_METADATA: str(part_size)},
            )
            upload_id = created["UploadId"]
        parts = []
        with _reopened(opened) as f:
            for number, digest in enumerate(digests, start=1):
                etag = stored.get(number)
                if etag is not None:
                    self._counts["parts_reused"] += 1
                else:
                    f.seek((number - 1) * part_size)
                    self._paced(min(part_size, size - (number - 1) * part_size), key)
                    answer = self._client.upload_part(
                        Bucket=p.bucket,
                        Key=key,
                        UploadId=upload_id,
                        PartNumber=number,
                        Body=f.read(part_size),
                        ContentMD5=_b64(digest),
                    )
                    etag = answer["ETag"]
                parts.append({"PartNumber": number, "ETag": etag})
        self._client.complete_multipart_upload(
            Bucket=p.bucket, Key=key, UploadId=upload_id, MultipartUpload={"Parts": parts}
        )

    def _resumable(
        self, key: str, size: int, part_size: int, digests: list[bytes]
    ) -> tuple[str | None, dict[int, str]]:
        """An unfinished upload of ``key`` cut in the same parts, with the parts it holds with the file's
        content (number -> ETag); others of the same key are aborted."""
        p = self.params
        try:
            uploads = [
                upload
                for page in self._client.get_paginator("list_multipart_uploads").paginate(Bucket=p.bucket, Prefix=key)
                for upload in page.get("Uploads", [])
                if upload.get("Key") == key
            ]
        except ClientError as exc:
            if store_failure(exc, self.where, "").kind in ("credentials", "object"):
                return None, {}  # not allowed to list uploads, or not implemented: upload afresh
            raise
        uploads.sort(key=lambda upload: str(upload.get("Initiated", "")), reverse=True)
        chosen: str | None = None
        kept: dict[int, str] = {}
        last_size = size - (len(digests) - 1) * part_size
        for upload in uploads:
            parts = [
                part
                for page in self._client.get_paginator("list_parts").paginate(
                    Bucket=p.bucket, Key=key, UploadId=upload["UploadId"]
                )
                for part in page.get("Parts", [])
            ]
            sizes_fit = all(
                1 <= part["PartNumber"] <= len(digests)
                and part["Size"] == (last_size if part["PartNumber"] == len(digests) else part_size)
                for part in parts
            )
            if chosen is None and sizes_fit:
                chosen = upload["UploadId"]
                kept = {
                    part["PartNumber"]: part["ETag"]
                    for part in parts
                    if part["ETag"].strip('"') == digests[part["PartNumber"] - 1].hex()
                }
                continue
            # Cut in other parts (another part_size, another file), or a second upload of the key:
            # never completed, its parts would be kept (and billed) until a lifecycle rule removes them.
            with contextlib.suppress(ClientError):
                self._client.abort_multipart_upload(Bucket=p.bucket, Key=key, UploadId=upload["UploadId"])
        return chosen, kept

    def _delete(self, files: list[OpenedFile]) -> None:
        for opened in files:
            path = opened.path
            try:
                if not delete_opened(opened):
                    continue  # gone, or the name now holds another file: not the one uploaded
            except OSError as exc:
                self._counts["delete_failures"] += 1
                self.context.logger.warning(f"{path} is stored in {self.where} but cannot be deleted: {exc.strerror}")
                continue
            self._counts["files_deleted"] += 1

    # -- messages ----------------------------------------------------------------------------------
    def _fail(self, exc: Exception, doing: str) -> NoReturn:
        failure = store_failure(exc, self.where, doing)
        if failure.kind == "no-bucket":
            self._bucket_ready = False  # deleted since it was looked up: create it again
        if failure.whole_store:
            raise StoreUnavailable(failure) from None
        raise RetryableError(self._scrub(failure.message)) from None

    def _problem(self, kind: str, message: str) -> None:
        """Log a store failure once when it starts (the server logs the retries per burst)."""
        if kind != self._last_problem:
            self.context.logger.error(message)
            self._last_problem = kind

    def _scrub(self, text: str) -> str:
        secret = self.params.secret_access_key
        return text.replace(secret, "***") if secret else text


def _reopened(opened: OpenedFile) -> Any:
    """A file object over (a duplicate of) the opened file's descriptor, at its start: boto3 reads and rewinds it."""
    f = os.fdopen(os.dup(opened.fd), "rb")
    f.seek(0)
    return f


def _age(seen: os.stat_result) -> float:
    return (time.time_ns() - seen.st_mtime_ns) / 1e9


def _same(before: os.stat_result, after: os.stat_result) -> bool:
    return (before.st_ino, before.st_size, before.st_mtime_ns) == (after.st_ino, after.st_size, after.st_mtime_ns)


def _b64(digest: bytes) -> str:
    return base64.b64encode(digest).decode("ascii")
