"""Images from the bucket, fetched by the dashboard and passed on: the browser never sees a key or a signature.

Only keys of images the pages link to are asked for (a .png or .jpg key), only objects whose bytes
are really PNG or JPEG are passed on, with the type their bytes say, and never more than
MAX_IMAGE_BYTES.
"""

from __future__ import annotations

from typing import Any

from dc_dashboard.errors import DashboardError
from dc_dashboard.settings import S3Settings

MAX_IMAGE_BYTES = 20 * 1024 * 1024
_SIGNATURES = {b"\x89PNG\r\n\x1a\n": "image/png", b"\xff\xd8\xff": "image/jpeg"}
_SUFFIXES = (".png", ".jpg", ".jpeg")


def image_type(head: bytes) -> str | None:
    """The content type the bytes are, PNG or JPEG; None for anything else."""
    for signature, content_type in _SIGNATURES.items():
        if head.startswith(signature):
            return content_type
    return None


class ImageStore:
    def __init__(self, settings: S3Settings) -> None:
        self.settings = settings
        self._client: Any = None

    def _s3(self) -> Any:
        if self._client is None:
            try:
                import boto3
                import botocore.config
            except ImportError:
                raise DashboardError('boto3 is not installed (pip install "ros2-dc[aws]")') from None
            config = botocore.config.Config(
                region_name=self.settings.region,
                connect_timeout=5,
                read_timeout=10,
                retries={"total_max_attempts": 2},
                s3={"addressing_style": "path"},
            )
            self._client = boto3.session.Session().client(
                "s3",
                endpoint_url=self.settings.endpoint or None,
                aws_access_key_id=self.settings.access_key_id or None,
                aws_secret_access_key=self.settings.secret_access_key or None,
                config=config,
            )
        return self._client

    def check_bucket(self) -> str | None:
        """None when the bucket answers; otherwise what is wrong, for the page."""
        if not self.settings.configured:
            return "no S3 bucket set (--s3-bucket or DC_S3_BUCKET): images cannot be shown"
        try:
            self._s3().head_bucket(Bucket=self.settings.bucket)
        except DashboardError as exc:
            return str(exc)
        except Exception as exc:  # botocore raises many unrelated types; all mean the same here
            return f"S3 bucket {self.settings.bucket!r} at {self.settings.endpoint or 'AWS'}: {_reason(exc)}"
        return None

    def image(self, key: str) -> tuple[bytes, str]:
        """The object's bytes and content type; DashboardError if it is missing, too large or not an image."""
        if not self.settings.configured:
            raise DashboardError("no S3 bucket set")
        if not key or not key.lower().endswith(_SUFFIXES) or ".." in key.split("/"):
            raise DashboardError("not an image key")
        try:
            response = self._s3().get_object(Bucket=self.settings.bucket, Key=key)
            length = int(response.get("ContentLength") or 0)
            if length > MAX_IMAGE_BYTES:
                raise DashboardError(f"{key}: {length} bytes, more than the dashboard passes on")
            body = response["Body"].read(MAX_IMAGE_BYTES + 1)
        except DashboardError:
            raise
        except Exception as exc:
            raise DashboardError(f"S3 bucket {self.settings.bucket!r}, {key}: {_reason(exc)}") from None
        content_type = image_type(body[:8])
        if content_type is None or len(body) > MAX_IMAGE_BYTES:
            raise DashboardError(f"{key} is not a PNG or JPEG image")
        return body, content_type


def _reason(exc: Exception) -> str:
    response = getattr(exc, "response", None)
    if isinstance(response, dict):
        error = response.get("Error", {})
        code, message = error.get("Code", ""), error.get("Message", "")
        if code in ("404", "NoSuchBucket", "NoSuchKey"):
            return "no such object" if code == "NoSuchKey" else "not found"
        return f"{code} {message}".strip() or type(exc).__name__
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
