"""One error root for DC; configuration errors carry the YAML path of the offending key."""

from __future__ import annotations


class DcError(Exception):
    """Base of every error DC raises on purpose."""


class ConfigError(DcError):
    """A configuration value is missing, unknown or of the wrong type or range."""

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path
        self.message = message


class PluginError(DcError):
    """A plugin could not be found, loaded or configured."""
