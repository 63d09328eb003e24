"""What the AWS destinations (KinesisStreams, S3, and the S3 stores of MinIO and FilesMetrics) share:
their client parameters, boto3 sessions and clients, endpoint and name checks, and which of boto3's
errors mean what. botocore's client configuration is made here only (:func:`make_client`).

Credentials come from boto3's default chain (environment, shared profile, instance or task role)
unless keys are given; with ``role_arn`` those only serve to assume the role through STS, and its
temporary credentials are refreshed before they expire.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

from dc_core.destination import Destination
from dc_core.errors import ConfigError
from dc_core.logs import Logger
from dc_core.params import param
from dc_destinations.settings import parse_size
from dc_destinations.tls import url_host, url_is_verified_tls, warn_if_credentials_in_clear

try:
    import boto3
    import botocore.config
    import botocore.credentials
    import botocore.exceptions
    import botocore.session
except ImportError as exc:  # an optional dependency: say which extra brings it
    raise ImportError(
        f"the AWS and S3-compatible destinations (KinesisStreams, S3, MinIO, FilesMetrics) need boto3: "
        f"pip install 'ros2-dc[aws]' ({exc})"
    ) from exc

# What the destinations catch, from here: importing this module is what says which extra brings boto3.
ClientError = botocore.exceptions.ClientError
BotoCoreError = botocore.exceptions.BotoCoreError

# Whole-request errors about who is calling: fixed by an operator (keys, role, policy), not by the records.
CREDENTIAL_CODES = frozenset(
    {
        "AccessDeniedException",
        "AccessDenied",
        "UnrecognizedClientException",
        "InvalidSignatureException",
        "SignatureDoesNotMatch",
        "ExpiredTokenException",
        "ExpiredToken",
        "InvalidClientTokenId",
        "IncompleteSignature",
        "MissingAuthenticationToken",
    }
)
# S3 names a wrong key ID its own way, on top of the codes every AWS service uses ("403": a HEAD's answer).
S3_CREDENTIAL_CODES = CREDENTIAL_CODES | {"InvalidAccessKeyId", "InvalidToken", "TokenRefreshRequired", "403"}
NETWORK_ERRORS = (
    botocore.exceptions.EndpointConnectionError,
    botocore.exceptions.ConnectTimeoutError,
    botocore.exceptions.ReadTimeoutError,
    botocore.exceptions.ConnectionClosedError,
)
CREDENTIALS_MISSING = (botocore.exceptions.NoCredentialsError, botocore.exceptions.PartialCredentialsError)

# S3's limits: parts of 5 MiB to 5 GiB (the last one smaller), at most 10000 of them, 5 GiB in one PUT.
MIN_PART_BYTES = 5 * 1024 * 1024
MAX_PART_BYTES = 5 * 1024 * 1024 * 1024
MAX_PARTS = 10_000
MAX_PUT_BYTES = 5 * 1024 * 1024 * 1024

_REGION = re.compile(r"[a-z]{2,}(-[a-z0-9]+)*(-\d+)?")
_BUCKET = re.compile(r"[a-z0-9][a-z0-9.-]{1,61}[a-z0-9]")
ROLE_ARN = re.compile(r"arn:aws[a-z-]*:iam::\d{12}:role/[\w+=,.@/-]+")
EXTERNAL_ID = re.compile(r"[\w+=,.@:/-]{2,1224}")


def region_problem(region: str) -> str | None:
    return None if _REGION.fullmatch(region) else 'an AWS region such as "eu-west-1"'


def size_problem(text: str) -> str | None:
    """For sizes of objects and parts, where nothing (0) makes no sense."""
    try:
        size = parse_size(text)
    except ConfigError:
        size = None
    return None if size else 'a size such as "64M", "16M" or a number of bytes'


def bucket_problem(bucket: str) -> str | None:
    if _BUCKET.fullmatch(bucket) and ".." not in bucket:
        return None
    if bucket == "dc_bucket":
        return 'a bucket name: the original\'s default "dc_bucket" is not one (no "_" in bucket names), use "dc-bucket"'
    return "a bucket name (3 to 63 lowercase letters, digits, '.', '-')"


def endpoint_url(value: str, use_ssl: bool = True) -> str | None:
    """An endpoint parameter as a URL: a URL as it is; a host (Fluent Bit's) or host:port (the original
    MinIO plugin's) with https, or http when ``use_ssl`` is false; None when empty (the region's)."""
    if not value:
        return None
    if "://" in value:
        return value
    return f"{'https' if use_ssl else 'http'}://{value}"


def check_credentials(access_key: str, secret_key: str, role_arn: str, external_id: str, sts_endpoint: str) -> None:
    """ConfigError, naming the key, for credentials parameters that do not go together."""
    if bool(access_key) != bool(secret_key):
        raise ConfigError(
            "aws_secret_access_key" if access_key else "aws_access_key_id",
            "set aws_access_key_id and aws_secret_access_key together (or neither: boto3's default chain)",
        )
    if role_arn and not ROLE_ARN.fullmatch(role_arn):
        raise ConfigError(
            "role_arn", f'expected an IAM role ARN (arn:aws:iam::<account>:role/<name>), got "{role_arn}"'
        )
    if external_id and not role_arn:
        raise ConfigError("external_id", "set role_arn too (the external ID goes with the role to assume)")
    if external_id and not EXTERNAL_ID.fullmatch(external_id):
        raise ConfigError("external_id", "expected 2 to 1224 characters among letters, digits and +=,.@:/-")
    if sts_endpoint and not role_arn:
        raise ConfigError("sts_endpoint", "set role_arn too (STS is only called to assume a role)")


@dataclass(frozen=True, kw_only=True)
class AwsCredentialsParams:
    """The credentials parameters every AWS destination takes (Fluent Bit's names), checked together."""

    sts_endpoint: str = param("", doc="STS endpoint for role_arn (host name or URL); empty: the region's")
    role_arn: str = param("", doc="IAM role to assume; empty: use the credentials as they are")
    external_id: str = param("", doc="External ID required by the role's trust policy (with role_arn)")
    aws_access_key_id: str = param("", doc="Access key ID; empty: boto3's default chain (env, profile, instance role)")
    aws_secret_access_key: str = param("", secret=True, doc="Secret access key with aws_access_key_id (never logged)")

    def __post_init__(self) -> None:
        check_credentials(
            self.aws_access_key_id, self.aws_secret_access_key, self.role_arn, self.external_id, self.sts_endpoint
        )

    def _warn_if_in_clear(self, logger: Logger, destination: str, endpoint: str) -> None:
        """The shared warning (:func:`warn_if_signed_in_clear`) for an endpoint override (or STS's) over plain HTTP.

        STS's answer holds temporary credentials, in clear too.
        """
        key = self.aws_access_key_id or "(from boto3's chain)"
        for url, what in ((endpoint_url(endpoint), "requests"), (endpoint_url(self.sts_endpoint), "STS requests")):
            warn_if_signed_in_clear(
                logger,
                destination,
                url,
                signed=f"{what} signed with access key {key}",
                fix="use an https:// endpoint (a host name without a scheme is https)",
            )

    def session(self, name: str, region: str, timeout: float) -> Any:
        """A boto3 session with these credentials (see :func:`aws_session`)."""
        return aws_session(
            name=name,
            region=region,
            access_key=self.aws_access_key_id,
            secret_key=self.aws_secret_access_key,
            role_arn=self.role_arn,
            external_id=self.external_id,
            sts_endpoint=self.sts_endpoint,
            timeout=timeout,
        )


@dataclass(frozen=True, kw_only=True)
class AwsClientParams(AwsCredentialsParams):
    """What a destination calling one AWS service takes (Fluent Bit's names), and the client made of it."""

    region: str = param("us-east-1", check=region_problem, doc="AWS region of the service")
    endpoint: str = param("", doc="Service endpoint (host name or URL; S3: path-style requests); empty: the region's")
    auto_retry_requests: bool = param(True, doc="Retry a failed request once at once, before the backoff")
    timeout: float = param(10.0, minimum=0.1, maximum=3600, doc="Seconds to connect and for each read")
    log_key: str = param("", doc="Send only this key's value instead of the whole record; empty: the whole record")

    def where(self, what: str) -> str:
        """'<what> in <region>[ at <endpoint>]': named in every message, so an operator sees what to fix."""
        endpoint = endpoint_url(self.endpoint)
        return f"{what} in {self.region}" + (f" at {endpoint}" if endpoint else "")

    def client(self, service: str, logger: Logger, name: str) -> Any:
        """A boto3 client of ``service`` for destination ``name``, after the warning about an endpoint
        in clear; making it reads configuration only, nothing is sent."""
        self._warn_if_in_clear(logger, name, self.endpoint)
        endpoint = endpoint_url(self.endpoint)
        return make_client(
            service,
            session=self.session(name, self.region, self.timeout),
            region=self.region,
            endpoint=endpoint,
            timeout=self.timeout,
            # Fluent Bit's auto_retry_requests: one immediate retry; the destination server's backoff does the rest.
            attempts=2 if self.auto_retry_requests else 1,
            # S3-compatible stores (SeaweedFS, MinIO, Ceph) rarely resolve bucket.host names: path-style there.
            addressing_style=("path" if endpoint else "auto") if service == "s3" else None,
        )

    def common_failure(self, exc: Exception, service: str, where: str) -> str | None:
        """The message of a failure every AWS destination words alike (role, credentials, network),
        scrubbed; None for the service's own answers."""
        if isinstance(exc, botocore.exceptions.ClientError) and exc.operation_name == "AssumeRole":
            error = exc.response.get("Error", {})
            code, text = str(error.get("Code", "")), str(error.get("Message", ""))
            return self.scrub(f"cannot assume role {self.role_arn}: {code}: {text} (for {where})")
        if isinstance(exc, CREDENTIALS_MISSING):
            return (
                f"no AWS credentials for {where}: set them in the environment, a profile, an instance "
                "role, or aws_access_key_id / aws_secret_access_key"
            )
        if isinstance(exc, NETWORK_ERRORS):
            return self.scrub(f"cannot reach {service} for {where}: {exc}")
        return None

    def scrub(self, text: str) -> str:
        """``text`` without the secret key (an error message may quote a request)."""
        secret = self.aws_secret_access_key
        return text.replace(secret, "***") if secret else text


AwsParamsT = TypeVar("AwsParamsT", bound=AwsClientParams)


class AwsDestination(Destination[AwsParamsT]):
    """What KinesisStreams and S3 share around their one boto3 client of ``service``.

    The client is made at configure time (reading the configuration and credentials chain only:
    nothing is sent) and kept (Destination.keep): deactivate and cleanup close its connections, and
    botocore opens them again on the next request. A failure is logged once when it starts and once
    when it ends; the destination server logs the retries per burst.
    """

    service: ClassVar[str]

    def __init__(self, context: Any, params: AwsParamsT, *, target: str) -> None:
        """``target``: what the records go to ("stream dc", "bucket logs"), named in every message."""
        super().__init__(context, params)
        self._client: Any = None
        self._last_problem = ""
        self.where = params.where(target)

    def on_configure(self) -> None:
        self._client = self.keep(self.params.client(self.service, self.context.logger, self.context.name))

    def _problem(self, message: str) -> None:
        if message != self._last_problem:
            self.context.logger.error(message)
            self._last_problem = message

    def _works_again(self, what: str) -> None:
        """After a logged failure: say once that ``what`` ("records accepted") goes through again."""
        if self._last_problem:
            self.context.logger.info(f"{self.where}: {what} again")
            self._last_problem = ""


def make_client(
    service: str,
    *,
    session: Any,
    region: str,
    endpoint: str | None,
    timeout: float,
    attempts: int | None,
    addressing_style: str | None = None,
) -> Any:
    """A boto3 client of ``session``; ``attempts`` None keeps botocore's retries (STS)."""
    options: dict[str, Any] = {}
    if attempts is not None:
        options["retries"] = {"total_max_attempts": attempts, "mode": "standard"}
    if addressing_style is not None:
        options["s3"] = {"addressing_style": addressing_style}
    config = botocore.config.Config(
        region_name=region,
        connect_timeout=timeout,
        read_timeout=timeout,
        # DC's own requests say who sends them (STS's never did).
        user_agent_extra="dc-destinations" if attempts is not None else None,
        **options,
    )
    return session.client(service, endpoint_url=endpoint, config=config)


def warn_if_signed_in_clear(logger: Logger, destination: str, url: str | None, *, signed: str, fix: str) -> bool:
    """The shared warning (dc_destinations.tls) for signed requests to ``url`` over plain HTTP.

    Requests are signed, not carrying the secret key, but the access key, the signed requests and
    what they carry travel readable, and a signed request can be replayed within minutes. ``url``
    None is AWS's own endpoint: https, checked by boto3.
    """
    if url is None:
        return False
    return warn_if_credentials_in_clear(
        logger, destination, url_host(url), credentials=signed, verified_tls=url_is_verified_tls(url), fix=fix
    )


def aws_session(
    *,
    name: str,
    region: str,
    access_key: str,
    secret_key: str,
    role_arn: str = "",
    external_id: str = "",
    sts_endpoint: str = "",
    timeout: float = 10.0,
) -> Any:
    """A boto3 session: the given keys or boto3's default chain, optionally assuming ``role_arn`` (refreshed)."""
    base = boto3.session.Session(
        aws_access_key_id=access_key or None, aws_secret_access_key=secret_key or None, region_name=region
    )
    if not role_arn:
        return base
    sts = make_client(
        "sts", session=base, region=region, endpoint=endpoint_url(sts_endpoint), timeout=timeout, attempts=None
    )
    session_name = re.sub(r"[^\w+=,.@-]", "-", f"dc-{name}")[:64]

    def assume_role() -> dict[str, str]:
        request = {"RoleArn": role_arn, "RoleSessionName": session_name}
        if external_id:
            request["ExternalId"] = external_id
        credentials = sts.assume_role(**request)["Credentials"]
        return {
            "access_key": credentials["AccessKeyId"],
            "secret_key": credentials["SecretAccessKey"],
            "token": credentials["SessionToken"],
            "expiry_time": credentials["Expiration"].isoformat(),
        }

    # Deferred: STS is called with the first upload, and again shortly before the credentials expire.
    core = botocore.session.get_session()
    core._credentials = botocore.credentials.DeferredRefreshableCredentials(
        refresh_using=assume_role, method="assume-role"
    )
    return boto3.session.Session(botocore_session=core, region_name=region)
