"""The one table of content types: what MinIO/S3 uploads send as Content-Type and FilesMetrics records.

Both read it, so an object's Content-Type and its files_metrics row never disagree.
"""

from __future__ import annotations

import mimetypes
import os

OCTET_STREAM = "application/octet-stream"
# Types of DC's own files that mimetypes does not know everywhere (it reads the system's tables) or
# takes for something else (.ts, IpCamera's video segments, is a Qt translation file to it).
_DC_TYPES = {".yaml": "application/yaml", ".yml": "application/yaml", ".ts": "video/mp2t"}


def content_type(path: str) -> str:
    """The MIME type the file's name suggests (DC's own types first, then the system's), else octet-stream.

    By name rather than by content: the file may already be gone (deleted once stored) when its row
    is written again.
    """
    extension = os.path.splitext(path)[1].lower()
    guessed, _encoding = mimetypes.guess_type(path, strict=False)
    return _DC_TYPES.get(extension) or guessed or OCTET_STREAM
