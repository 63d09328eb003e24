"""dc_core.stamped_cdr: the stamp and text of a serialised StringStamped, exactly as rclpy reads them."""

from __future__ import annotations

import random
from collections.abc import Callable

import pytest
from rclpy.serialization import deserialize_message, serialize_message

from dc_core.stamped_cdr import read_string_stamped
from dc_interfaces.msg import StringStamped


def _message(data: str, frame_id: str = "", group_key: str = "", sec: int = 0, nanosec: int = 0) -> StringStamped:
    msg = StringStamped()
    msg.data, msg.header.frame_id, msg.group_key = data, frame_id, group_key
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    return msg


def _as_rclpy_reads(serialised: bytes) -> tuple[int, str]:
    msg = deserialize_message(serialised, StringStamped)
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, msg.data


def _text(rng: random.Random, length: int) -> str:
    ranges = [(1, 0x7F), (0x80, 0xD7FF), (0xE000, 0x10FFFF)]
    return "".join(chr(rng.randint(*rng.choice(ranges))) for _ in range(length))


def test_any_message_reads_as_rclpy_reads_it() -> None:
    rng = random.Random(7)
    for _ in range(2000):
        msg = _message(
            _text(rng, rng.randint(0, 40)),
            _text(rng, rng.randint(0, 7)),  # every padding before data
            _text(rng, rng.randint(0, 5)),
            rng.randint(-(2**31), 2**31 - 1),
            rng.randint(0, 2**32 - 1),
        )
        serialised = serialize_message(msg)
        assert read_string_stamped(serialised) == _as_rclpy_reads(serialised)


@pytest.mark.parametrize(
    ("patch", "expected"),
    [((1, 0), "a"), ((2, 0xFF), "ab\ufffddef")],
    ids=["nul-ends-the-string", "invalid-utf8-replaced"],
)
def test_bytes_rclpy_reads_its_own_way(patch: tuple[int, int], expected: str) -> None:
    serialised = bytearray(serialize_message(_message("abcdef")))
    offset, value = patch
    serialised[serialised.index(b"abcdef") + offset] = value
    assert read_string_stamped(bytes(serialised)) == _as_rclpy_reads(bytes(serialised)) == (0, expected)


def _outcome(read: Callable[[bytes], tuple[int, str]], serialised: bytes) -> object:
    try:
        return read(serialised)
    except Exception as exc:  # the failure itself is what is compared
        return type(exc)


@pytest.mark.parametrize("case", ["truncated", "other-encapsulation", "big-endian"])
def test_what_it_does_not_read_itself_is_rclpy_s_to_read(case: str) -> None:
    serialised = serialize_message(_message('{"a": 1}', "frame", sec=5, nanosec=7))
    if case == "truncated":
        serialised = serialised[: serialised.index(b"{") + 2]
    elif case == "other-encapsulation":
        serialised = b"\x00\x07" + serialised[2:]
    else:
        serialised = b"\x00\x00" + serialised[2:]  # the same bytes read big-endian: lengths out of range
    assert _outcome(read_string_stamped, serialised) == _outcome(_as_rclpy_reads, serialised)
