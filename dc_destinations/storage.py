"""Where the delivery buffer lives: ``flb.storage_path``, else the default folder of the user's data."""

from __future__ import annotations

import os
from pathlib import Path

from dc_core.logs import Logger
from dc_core.paths import expand_env
from dc_destinations.settings import DeliveryParams

# What each storage_sync promises, as the server says it at start.
SYNC_PROMISE = {
    "normal": "committed records survive a crash of the process, a power cut may lose the last ones",
    "full": "committed records survive a crash of the process and a power cut",
}


def default_storage_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(base) / "dc" / "buffer"


def storage_dir(settings: DeliveryParams, logger: Logger) -> Path:
    """The buffer's folder, created; the default one when the configured folder cannot be used (logged)."""
    configured = settings.storage_path.strip()
    if not configured:
        directory = default_storage_dir()
        directory.mkdir(parents=True, exist_ok=True)
        return directory
    directory = Path(os.path.expanduser(expand_env(configured, "destination_server.flb.storage_path")))
    try:
        directory.mkdir(parents=True, exist_ok=True)
        if not os.access(directory, os.W_OK | os.X_OK):
            raise PermissionError(f"{directory} is not writable")
    except OSError as exc:
        fallback = default_storage_dir()
        logger.error(f"flb.storage_path {directory} cannot be used ({exc}); buffering in {fallback} instead")
        fallback.mkdir(parents=True, exist_ok=True)
        return fallback
    return directory
