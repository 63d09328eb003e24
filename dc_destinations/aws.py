"""What the AWS destinations (KinesisStreams, S3) share: boto3 sessions, endpoint and name checks, and
which of boto3's errors mean what.

Credentials come from boto3's default chain (environment, shared profile, instance or task role)
unless keys are given; with ``role_arn`` those only serve to assume the role through STS, and its
temporary credentials are refreshed before they expire.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from dc_core.errors import ConfigError
from dc_core.logs import Logger
from dc_core.params import param
from dc_destinations.tls import url_host, url_is_verified_tls, warn_if_credentials_in_clear

try:
    import boto3
    import botocore.config
    import botocore.credentials
    import botocore.exceptions
    import botocore.session
except ImportError as exc:  # an optional dependency: say which extra brings it
    raise ImportError(
        f"the AWS destinations (KinesisStreams, S3) need boto3: pip install 'ros2-dc[aws]' ({exc})"
    ) from exc

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
NETWORK_ERRORS = (
    botocore.exceptions.EndpointConnectionError,
    botocore.exceptions.ConnectTimeoutError,
    botocore.exceptions.ReadTimeoutError,
    botocore.exceptions.ConnectionClosedError,
)
CREDENTIALS_MISSING = (botocore.exceptions.NoCredentialsError, botocore.exceptions.PartialCredentialsError)

_REGION = re.compile(r"[a-z]{2,}(-[a-z0-9]+)*(-\d+)?")
ROLE_ARN = re.compile(r"arn:aws[a-z-]*:iam::\d{12}:role/[\w+=,.@/-]+")
EXTERNAL_ID = re.compile(r"[\w+=,.@:/-]{2,1224}")


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

    def warn_if_in_clear(self, logger: Logger, destination: str, endpoint: str) -> None:
        """The shared warning (dc_destinations.tls) for an endpoint override (or STS's) over plain HTTP.

        Requests are signed, not carrying the secret key, but the access key, the signed requests and
        the records travel readable (and STS's answer holds temporary credentials in clear).
        """
        key = self.aws_access_key_id or "(from boto3's chain)"
        for url, what in ((endpoint_url(endpoint), "requests"), (endpoint_url(self.sts_endpoint), "STS requests")):
            if url is not None:
                warn_if_credentials_in_clear(
                    logger,
                    destination,
                    url_host(url),
                    credentials=f"{what} signed with access key {key}",
                    verified_tls=url_is_verified_tls(url),
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


def region_problem(region: str) -> str | None:
    return None if _REGION.fullmatch(region) else 'an AWS region such as "eu-west-1"'


def endpoint_url(value: str) -> str | None:
    """Fluent Bit's ``endpoint`` is a host name (HTTPS); a URL is taken as is."""
    if not value:
        return None
    return value if "://" in value else f"https://{value}"


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
    sts = base.client(
        "sts",
        endpoint_url=endpoint_url(sts_endpoint),
        config=botocore.config.Config(region_name=region, connect_timeout=timeout, read_timeout=timeout),
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
