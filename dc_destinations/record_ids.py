"""Record ids: one UUIDv7 per received record, shared by its copies, kept in the delivered JSON.

Sinks deduplicate on it what at-least-once delivery may send twice; time-ordered, it also sorts
records by arrival and keeps B-tree indexes of a sink's ``record_id`` column compact.
"""

from __future__ import annotations

import os
import threading
import time
import uuid


class _Uuid7Source:
    """RFC 9562 UUIDv7: 48-bit Unix milliseconds, then a 12-bit counter that keeps ids from one
    process increasing within a millisecond, then 62 random bits.

    The random bits come from the operating system's CSPRNG, read 4 KiB at a time: one getrandom()
    per id was a system call on the intake's hot path, where each one also lets the writer thread
    take the GIL. A forked child forgets the pool, so parent and child never share bits.
    """

    _POOL_BYTES = 4096

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last_ms = -1
        self._counter = 0
        self._pool = b""
        self._pool_pos = 0
        os.register_at_fork(after_in_child=self._forget_pool)

    def _forget_pool(self) -> None:
        self._pool, self._pool_pos = b"", 0

    def _random_bits(self, bits: int) -> int:
        """``bits`` (at most 64) random bits; call with the lock held."""
        if self._pool_pos + 8 > len(self._pool):
            self._pool, self._pool_pos = os.urandom(self._POOL_BYTES), 0
        word = int.from_bytes(self._pool[self._pool_pos : self._pool_pos + 8], "big")
        self._pool_pos += 8
        return word >> (64 - bits)

    def next(self) -> uuid.UUID:
        return uuid.UUID(int=self.next_int())

    def next_int(self) -> int:
        """The next UUIDv7 as its 128-bit integer."""
        with self._lock:
            ms = time.time_ns() // 1_000_000
            if ms > self._last_ms:
                self._last_ms = ms
                self._counter = self._random_bits(11)  # top bit clear leaves room to count up
            else:
                self._counter += 1
                if self._counter > 0xFFF:  # 4,096 ids in one millisecond: borrow the next one
                    self._last_ms += 1
                    self._counter = 0
            ms, counter = self._last_ms, self._counter
            random62 = self._random_bits(62)
        return (ms & 0xFFFF_FFFF_FFFF) << 80 | 0x7 << 76 | counter << 64 | 0b10 << 62 | random62


_UUID7 = _Uuid7Source()


def uuid7() -> uuid.UUID:
    return _UUID7.next()


def new_record_id() -> str:
    """A fresh ``record_id``: a UUIDv7 string, time-ordered, for sinks to deduplicate on."""
    # The text str(uuid.UUID) gives, without building the UUID object (a quarter of the time, per record).
    digits = f"{_UUID7.next_int():032x}"
    return f"{digits[:8]}-{digits[8:12]}-{digits[12:16]}-{digits[16:20]}-{digits[20:]}"
