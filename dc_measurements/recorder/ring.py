"""The recorder's memory: every message of its topics as received, newest last, bounded in bytes.

An entry is a tuple ``(receive_ns, publish_ns, topic_index, data)`` — the serialised message as the
subscription took it, never decoded. Two rules keep the ring small:

* age: what is older than ``keep_ns`` (the pre-trigger window) is let go, uncounted — unless an
  incident's window still needs it (``hold_from_ns``);
* bound: past ``max_bytes`` the oldest entries go first, counted per topic (``lost_to_bound``) and,
  when an open window needed them, in ``lost_in_window`` (the incident's record says its window was cut);
  those let go in the last ``keep_ns`` before any window opened are remembered (time and topic), so that
  a window opening later counts them too (:meth:`lost_since`).

A window whose file is being written keeps its messages in memory until the worker is done (``writing``):
those the ring lets go meanwhile still count in the bound (``held_out``), not as lost — so the messages in
memory, the ring's and the windows' being written together, stay under ``max_bytes``; while a large window
is written the ring holds that much less of what comes after it.

Messages of latched topics (transient-local publishers, ``/tf_static``) are also kept apart, the last
``LATCHED_KEEP`` of each, whatever their age: a window gets them however long before it they came.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

Entry = tuple[int, int, int, bytes]
# What an entry costs beyond its bytes: the tuple, two ints, the bytes object's header, the deque slot.
ENTRY_OVERHEAD = 160
# Each latching publisher re-sends its last message to a new subscriber: /tf_static has one per
# static transform broadcaster. More than this many on one topic keeps the newest.
LATCHED_KEEP = 64
NEVER = 1 << 62


@dataclass(eq=False)
class Writing:
    """A window whose file is being written (Ring.writing)."""

    start_ns: int
    end_ns: int
    held: set[int]  # id() of the entries its snapshot holds (the snapshot keeps them alive: ids stay unique)
    lost: list[int]  # per topic, entries of its time that the ring let go without the snapshot holding them
    held_out: int = field(default=0)  # bytes of the held entries that the ring let go since


class Ring:
    def __init__(self, max_bytes: int, keep_ns: int, topics: int) -> None:
        self.max_bytes = max_bytes
        self.keep_ns = keep_ns
        self.bytes = 0
        self._entries: deque[Entry] = deque()
        self._latched: dict[int, deque[Entry]] = {}
        self.hold_from_ns = NEVER
        self.lost_to_bound = [0] * topics
        self.lost_in_window = [0] * topics
        # Per window being written: [start_ns, end_ns, bytes of its messages the ring let go since].
        self._writing: list[Writing] = []
        self.held_out = 0
        # (receive_ns, topic) of the entries the bound let go outside a window, for keep_ns.
        self._lost_recently: deque[tuple[int, int]] = deque()

    def __len__(self) -> int:
        return len(self._entries)

    def append(self, receive_ns: int, publish_ns: int, topic: int, data: bytes, latched: bool = False) -> None:
        entry = (receive_ns, publish_ns, topic, data)
        entries = self._entries
        entries.append(entry)
        self.bytes += len(data) + ENTRY_OVERHEAD
        if latched:
            kept = self._latched.get(topic)
            if kept is None:
                kept = self._latched[topic] = deque(maxlen=LATCHED_KEEP)
            kept.append(entry)
        expired = min(receive_ns - self.keep_ns, self.hold_from_ns)
        while entries[0][0] < expired:
            self._let_go(entries.popleft())
        while self.bytes + self.held_out > self.max_bytes and entries:
            old = entries.popleft()
            if self._let_go(old):
                continue  # in a file being written: not lost, and still in memory until it is
            self.lost_to_bound[old[2]] += 1
            if old[0] >= self.hold_from_ns:
                self.lost_in_window[old[2]] += 1
            else:
                self._lost_recently.append((old[0], old[2]))
        recently = self._lost_recently
        while recently and recently[0][0] < receive_ns - self.keep_ns:
            recently.popleft()

    def lost_since(self, start_ns: int) -> list[int]:
        """Per topic, the entries received from ``start_ns`` on that the bound let go outside a window."""
        lost = [0] * len(self.lost_to_bound)
        for receive_ns, topic in self._lost_recently:
            if receive_ns >= start_ns:
                lost[topic] += 1
        return lost

    def _let_go(self, entry: Entry) -> bool:
        """Takes ``entry`` out of the ring; True if a window being written holds it. One of such a window's time
        that its snapshot does not hold (taken after it) is counted in the window's ``lost``."""
        size = len(entry[3]) + ENTRY_OVERHEAD
        self.bytes -= size
        for writing in self._writing:
            if id(entry) in writing.held:
                writing.held_out += size
                self.held_out += size
                return True
            if writing.start_ns <= entry[0] <= writing.end_ns:
                writing.lost[entry[2]] += 1
        return False

    def writing(self, start_ns: int, end_ns: int, entries: list[Entry]) -> Writing:
        """The window [start_ns, end_ns] is being written from ``entries`` (taken from :meth:`window`): what the
        ring lets go of them still counts in the bound until :meth:`written`."""
        writing = Writing(start_ns, end_ns, {id(e) for e in entries}, [0] * len(self.lost_to_bound))
        self._writing.append(writing)
        return writing

    def written(self, writing: Writing) -> None:
        if writing in self._writing:
            self._writing.remove(writing)
            self.held_out -= writing.held_out

    def oldest_ns(self) -> int | None:
        return self._entries[0][0] if self._entries else None

    def window(self, start_ns: int, end_ns: int) -> list[Entry]:
        """The latched entries received before ``start_ns`` (dated ``start_ns``, their publish time kept),
        then :meth:`between`."""
        earlier = [(start_ns, e[1], e[2], e[3]) for kept in self._latched.values() for e in kept if e[0] < start_ns]
        return earlier + self.between(start_ns, end_ns)

    def between(self, start_ns: int, end_ns: int) -> list[Entry]:
        """The entries received in [start_ns, end_ns], in the order they were taken."""
        return [e for e in self._entries if start_ns <= e[0] <= end_ns]

    def take_lost_in_window(self) -> list[int]:
        lost, self.lost_in_window = self.lost_in_window, [0] * len(self.lost_in_window)
        return lost

    def clear(self) -> None:
        self._entries.clear()
        self._latched.clear()
        self._writing.clear()
        self._lost_recently.clear()
        self.bytes = self.held_out = 0
