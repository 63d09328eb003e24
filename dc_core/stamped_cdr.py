"""``StringStamped`` read straight from the bytes DDS delivered, and written as the bytes to publish.

rclpy turns a taken message into Python objects (``StringStamped``, ``Header``, ``Time``: a
``__init__`` each, and their property setters), which cost a receiving server ~12 us a record
of its ~45 us take where reading the two fields from the serialised bytes takes ~1 us
(docs/performance.md). A server that takes its subscription ``raw`` reads it here. Publishing
goes the same way: a message built field by field and converted by rclpy cost 5 us where
:func:`write_string_stamped` and a raw publish take 1.9.

The layout is CDR's (XCDR1, the serialisation ROS 2's RMWs use for ROS types): a 4-byte
encapsulation header, then ``header.stamp.sec`` (int32), ``header.stamp.nanosec`` (uint32),
``header.frame_id`` and ``data``, each string a 4-byte-aligned uint32 length (NUL included) and
its bytes, then ``group_key`` the same way. Anything else — another encapsulation, a length
beyond the bytes — is handed to rclpy's own deserialisation, so that the result is always what
rclpy would have given. Written little-endian, with zeros as padding (DDS leaves it undefined).
"""

from __future__ import annotations

import struct
from typing import Any

from rclpy.serialization import deserialize_message, serialize_message

from dc_interfaces.msg import StringStamped

_LITTLE_ENDIAN = b"\x00\x01"
_BIG_ENDIAN = b"\x00\x00"
_STAMP = {_LITTLE_ENDIAN: struct.Struct("<iII"), _BIG_ENDIAN: struct.Struct(">iII")}
_LENGTH = {_LITTLE_ENDIAN: struct.Struct("<I"), _BIG_ENDIAN: struct.Struct(">I")}
_BODY = 4  # CDR aligns relative to the end of the encapsulation header


def read_string_stamped(serialised: bytes) -> tuple[int, str]:
    """``(header stamp in ns, data)`` of a serialised ``StringStamped``, as rclpy would read them.

    rclpy reads a string up to its first NUL (``strlen``) and decodes it with ``errors="replace"``:
    so does this.
    """
    fields = _read(serialised, False)
    if fields is None:
        stamp_ns, data, _ = _read_by_rclpy(serialised)
        return stamp_ns, data
    return fields[0], fields[1]


def read_stamped_record(serialised: bytes) -> tuple[int, str, str]:
    """``(header stamp in ns, data, group_key)`` of a serialised ``StringStamped``, as rclpy would read them."""
    fields = _read(serialised, True)
    return _read_by_rclpy(serialised) if fields is None else fields


def read_keyed_string_stamped(serialised: bytes) -> tuple[int, str, str]:
    """``(header stamp in ns, data, header.frame_id)``: the frame_id carries a hand-off key (dc_core.handoff)."""
    kind = serialised[:2]
    stamp = _STAMP.get(kind)
    if stamp is not None and len(serialised) >= _BODY + 12:
        frame_length = stamp.unpack_from(serialised, _BODY)[2]
        end = _BODY + 12 + frame_length
        fields = _read(serialised, False)
        if fields is not None and frame_length > 0:
            frame = serialised[_BODY + 12 : end - 1]
            nul = frame.find(0)
            return fields[0], fields[1], (frame[:nul] if nul >= 0 else frame).decode("utf-8", "replace")
    msg: Any = deserialize_message(serialised, StringStamped)
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, msg.data, msg.header.frame_id


def _read(serialised: bytes, with_group_key: bool) -> tuple[int, str, str] | None:
    """The fields read here, or None for bytes left to rclpy."""
    kind = serialised[:2]
    stamp = _STAMP.get(kind)
    if stamp is None or len(serialised) < _BODY + 12:
        return None
    sec, nanosec, frame_length = stamp.unpack_from(serialised, _BODY)
    length_of = _LENGTH[kind]
    data, at = _string_at(serialised, _BODY + 12 + frame_length, length_of)
    if data is None:
        return None
    group_key = ""
    if with_group_key:
        read_key, _ = _string_at(serialised, at, length_of)
        if read_key is None:
            return None
        group_key = read_key
    return sec * 1_000_000_000 + nanosec, data, group_key


def _string_at(serialised: bytes, at: int, length_of: struct.Struct) -> tuple[str | None, int]:
    """The string whose length is at ``at`` once aligned, and where the bytes after it start; None out of range."""
    at += -(at - _BODY) % 4
    if at + 4 > len(serialised):
        return None, at
    (length,) = length_of.unpack_from(serialised, at)
    start = at + 4
    end = start + length
    if end > len(serialised):
        return None, at
    nul = serialised.find(0, start, end)
    return serialised[start : nul if nul >= 0 else end].decode("utf-8", "replace"), end


def _read_by_rclpy(serialised: bytes) -> tuple[int, str, str]:
    msg: Any = deserialize_message(serialised, StringStamped)
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, msg.data, msg.group_key


# sec, nanosec, and the length of frame_id (with its NUL).
_WRITTEN_HEADER = struct.Struct("<iII")
_INT32 = range(-(2**31), 2**31)


def write_string_stamped(stamp_ns: int, data: str, group_key: str = "", frame_id: str = "") -> bytes:
    """A ``StringStamped`` serialised as rclpy would, for ``Publisher.publish``.

    A text that holds a NUL, and a stamp beyond the message's 32-bit seconds, are given to rclpy
    to serialise, which cuts a string at its NUL and refuses such a stamp; a text that is not
    valid Unicode (a lone surrogate) raises ``UnicodeEncodeError``, as rclpy does.
    """
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    encoded = data.encode("utf-8")
    key = group_key.encode("utf-8")
    frame = frame_id.encode("utf-8")
    if b"\0" in encoded or b"\0" in key or b"\0" in frame or sec not in _INT32:
        return _written_by_rclpy(sec, nanosec, data, group_key, frame_id)
    end_of_frame = 12 + len(frame) + 1  # from the body's start
    end_of_data = end_of_frame + -end_of_frame % 4 + 4 + len(encoded) + 1
    return b"".join(
        (
            _LITTLE_ENDIAN + b"\0\0",
            _WRITTEN_HEADER.pack(sec, nanosec, len(frame) + 1),
            frame,
            b"\0" * (1 + -end_of_frame % 4),
            _LENGTH[_LITTLE_ENDIAN].pack(len(encoded) + 1),
            encoded,
            b"\0" * (1 + -end_of_data % 4),
            _LENGTH[_LITTLE_ENDIAN].pack(len(key) + 1),
            key,
            b"\0",
        )
    )


def _written_by_rclpy(sec: int, nanosec: int, data: str, group_key: str, frame_id: str = "") -> bytes:
    msg = StringStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.header.frame_id = frame_id
    msg.data = data
    msg.group_key = group_key
    return bytes(serialize_message(msg))
