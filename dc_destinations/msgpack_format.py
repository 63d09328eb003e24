"""``format: msgpack`` of the destinations that offer it (TCP, HTTP): one encoding, one install hint."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from dc_core.errors import ConfigError


def msgpack_packer(path: str) -> Callable[[Any], bytes]:
    """MessagePack of record maps (strings as str, bytes as bin); a ConfigError at ``path`` (the
    destination's ``format``) when the optional package is not installed."""
    try:
        import msgpack  # an optional dependency: `pip install ros2-dc[msgpack]`
    except ImportError as exc:
        raise ConfigError(path, 'msgpack needs the msgpack package (pip install "ros2-dc[msgpack]")') from exc

    def pack(value: Any) -> bytes:
        packed: bytes = msgpack.packb(value, use_bin_type=True)
        return packed

    return pack
