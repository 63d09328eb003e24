"""dc_core.stamped_cdr: the stamp and text of a serialised StringStamped, exactly as rclpy reads them."""

from __future__ import annotations

import random
from collections.abc import Callable

import pytest
from rclpy.serialization import deserialize_message, serialize_message

from dc_core.stamped_cdr import read_stamped_record, read_string_stamped, write_string_stamped
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


def _outcome(read: Callable[[bytes], object], serialised: bytes) -> object:
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


def test_the_group_key_reads_as_rclpy_reads_it() -> None:
    rng = random.Random(11)
    for _ in range(500):
        msg = _message(
            _text(rng, rng.randint(0, 30)), _text(rng, rng.randint(0, 7)), _text(rng, rng.randint(0, 9)), 3, 4
        )
        serialised = serialize_message(msg)
        stamp_ns, data = _as_rclpy_reads(serialised)
        assert read_stamped_record(serialised) == (stamp_ns, data, msg.group_key)
    truncated = serialize_message(_message("abc", group_key="group"))[:-3]
    assert _outcome(read_stamped_record, truncated) == _outcome(
        lambda b: (*_as_rclpy_reads(b), deserialize_message(b, StringStamped).group_key), truncated
    )


def test_written_messages_are_what_rclpy_serialises() -> None:
    rng = random.Random(5)
    for _ in range(2000):
        stamp_ns = rng.randint(-(2**31) * 10**9, (2**31 - 1) * 10**9 + 999_999_999)
        data, group_key = _text(rng, rng.randint(0, 40)), _text(rng, rng.randint(0, 9))
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        expected = serialize_message(_message(data, group_key=group_key, sec=sec, nanosec=nanosec))
        written = write_string_stamped(stamp_ns, data, group_key)
        # Byte for byte but the padding, which DDS leaves undefined (zeros here).
        assert len(written) == len(expected)
        back = deserialize_message(written, StringStamped)
        assert (back.header.stamp.sec, back.header.stamp.nanosec, back.header.frame_id) == (sec, nanosec, "")
        assert (back.data, back.group_key) == (data, group_key)


def test_what_rclpy_would_write_its_own_way_it_writes() -> None:
    # A NUL cuts the string; a lone surrogate cannot be published; nor a stamp beyond int32 seconds.
    assert deserialize_message(write_string_stamped(0, "a\0b", "k\0"), StringStamped).data == "a"
    with pytest.raises(UnicodeEncodeError):
        write_string_stamped(0, "\udcff")
    too_late = 2**31 * 1_000_000_000

    def fields(write: Callable[[], bytes]) -> object:
        try:
            msg = deserialize_message(write(), StringStamped)
        except Exception as exc:  # the failure itself is what is compared
            return type(exc)
        return msg.header.stamp.sec, msg.header.stamp.nanosec, msg.data

    assert fields(lambda: write_string_stamped(too_late, "{}")) == fields(
        lambda: serialize_message(_message("{}", sec=2**31))
    )
