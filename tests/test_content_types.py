"""One content-type table for the object uploads and the files_metrics rows."""

from __future__ import annotations

import pytest

from dc_destinations import minio
from dc_destinations.content_types import content_type


@pytest.mark.parametrize(
    ("path", "expected"),
    [
        ("/d/segment_0001.ts", "video/mp2t"),  # IpCamera's segments, not a Qt translation file
        ("/d/map.YAML", "application/yaml"),
        ("/d/map.pgm", "image/x-portable-graymap"),
        ("/d/frame.jpg", "image/jpeg"),
        ("/d/blob.unknown-ext", "application/octet-stream"),
    ],
)
def test_a_files_type_is_the_same_wherever_it_is_told(path: str, expected: str) -> None:
    import dc_destinations.files_metrics as files_metrics

    assert content_type(path) == expected
    assert getattr(minio, "file_content_type") is content_type  # noqa: B009 (not an exported name)
    assert getattr(files_metrics, "content_type") is content_type  # noqa: B009
