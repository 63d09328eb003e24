"""Keys of a server's JSON metrics document (``/api/v1/metrics``) that its writer and readers share.

Standard library only: `dc status` and the dashboard read the documents without importing ROS.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def by_measurement_key(counter: str) -> str:
    """The key that holds ``counter`` per measurement name (``{name: count}``)."""
    return f"{counter}_by_measurement"


def per_measurement(document: Mapping[str, Any], counter: str) -> list[tuple[str, Any]]:
    """``counter`` per measurement in a metrics document, by measurement name; empty when it has none."""
    of = document.get(by_measurement_key(counter))
    return sorted(of.items()) if isinstance(of, Mapping) else []
