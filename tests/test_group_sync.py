"""The group synchroniser against hand-computed match sets (no ROS, injected clock, no sleeps).

Each scenario is a list of arrivals ``(arrival time s, input, stamp s)``; the expected sets were
worked out by hand from the rules in ``dc_group/sync.py``. Messages are named ``<input>@<stamp>``.
"""

from __future__ import annotations

import pytest

from dc_group.sync import ApproximateTimeSync, SyncedSet

NAMES = "ABC"


def ns(seconds: float) -> int:
    return round(seconds * 1e9)


def label(synced: SyncedSet[str]) -> tuple[str | None, ...]:
    return tuple(m.payload if m is not None else None for m in synced.members)


def make(inputs: int = 2, slop: float = 0.1, timeout: float = 100.0, queue_size: int = 10) -> ApproximateTimeSync[str]:
    return ApproximateTimeSync(inputs, slop_ns=ns(slop), timeout=timeout, queue_size=queue_size)


def drive(
    sync: ApproximateTimeSync[str], arrivals: list[tuple[float, int, float]]
) -> list[tuple[str, tuple[str | None, ...]]]:
    """Like the server: expire what is due, then offer; returns ("set" | "timeout", members)."""
    out: list[tuple[str, tuple[str | None, ...]]] = []
    for now, index, stamp in arrivals:
        out.extend(("timeout", label(s)) for s in sync.expire(now))
        synced = sync.offer(index, ns(stamp), f"{NAMES[index]}@{stamp:g}", now)
        if synced is not None:
            assert synced.complete
            out.append(("set", label(synced)))
    return out


def sets(*members: tuple[str | None, ...]) -> list[tuple[str, tuple[str | None, ...]]]:
    return [("set", m) for m in members]


def test_same_rate_with_jitter_pairs_the_nearest_stamps() -> None:
    sync = make(slop=0.1)
    arrivals = [
        (0.00, 0, 0.00), (0.01, 1, 0.01),
        (1.02, 0, 1.02), (1.03, 1, 0.99),
        (2.03, 1, 2.03), (2.04, 0, 1.98),
        (3.01, 0, 3.01), (3.02, 1, 2.97),
    ]  # fmt: skip
    assert drive(sync, arrivals) == sets(
        ("A@0", "B@0.01"), ("A@1.02", "B@0.99"), ("A@1.98", "B@2.03"), ("A@3.01", "B@2.97")
    )
    assert sync.pending_count() == 0


def test_different_rates_emit_once_per_slowest_message_with_its_nearest_partner() -> None:
    # The group demo: memory every second, uptime every 3 s, slop 5 s; memory arrives first.
    sync = make(slop=5.0, timeout=6.0)
    arrivals: list[tuple[float, int, float]] = []
    for t in range(10):
        arrivals.append((t, 0, t))
        if t % 3 == 0:
            arrivals.append((t + 0.001, 1, t))
    assert drive(sync, arrivals) == sets(("A@0", "B@0"), ("A@3", "B@3"), ("A@6", "B@6"), ("A@9", "B@9"))
    # A@1 A@2, A@4 A@5, A@7 A@8 went out of date when a newer A was used.
    assert sync.counters.superseded == 6
    assert sync.counters.incomplete_sets == 0


def test_a_set_is_emitted_as_soon_as_it_exists_without_waiting_for_a_closer_partner() -> None:
    # Same rates, but uptime arrives just before memory: B@3 pairs with the A already there (A@2).
    sync = make(slop=5.0, timeout=6.0)
    arrivals: list[tuple[float, int, float]] = []
    for t in range(10):
        if t % 3 == 0:
            arrivals.append((t, 1, t))
        arrivals.append((t + 0.001, 0, t))
    assert drive(sync, arrivals) == sets(("A@0", "B@0"), ("A@2", "B@3"), ("A@5", "B@6"), ("A@8", "B@9"))
    # A@3 is left pending, newer than the A used with B@3; it is superseded when A@5 is used.
    assert sync.pending_count() == 1  # A@9


def test_out_of_order_arrival_within_an_input_matches_by_stamp() -> None:
    sync = make(slop=0.1)
    arrivals = [(0.0, 0, 2.0), (0.1, 0, 1.0), (0.2, 1, 1.0), (0.3, 1, 2.0)]
    assert drive(sync, arrivals) == sets(("A@1", "B@1"), ("A@2", "B@2"))


def test_out_of_order_arrival_across_inputs() -> None:
    # B's message stamped 1 arrives after A's stamped 2: both sets still form.
    sync = make(slop=0.1)
    arrivals = [(1.0, 0, 1.0), (2.0, 0, 2.0), (2.1, 1, 1.0), (2.2, 1, 2.0)]
    assert drive(sync, arrivals) == sets(("A@1", "B@1"), ("A@2", "B@2"))


def test_equal_spreads_prefer_the_later_stamps() -> None:
    sync = make(slop=1.5)
    arrivals = [(0.0, 1, 4.0), (0.1, 1, 6.0), (0.2, 0, 5.0)]
    assert drive(sync, arrivals) == sets(("A@5", "B@6"))
    assert sync.counters.superseded == 1  # B@4


def test_slop_is_inclusive() -> None:
    sync = make(slop=0.5)
    assert drive(sync, [(0.0, 0, 10.0), (0.1, 1, 10.5)]) == sets(("A@10", "B@10.5"))
    sync = make(slop=0.5)
    sync.offer(0, ns(10.0), "A@10", 0.0)
    assert sync.offer(1, ns(10.0) + ns(0.5) + 1, "B", 0.1) is None


def test_zero_slop_needs_equal_stamps() -> None:
    sync = make(slop=0.0)
    arrivals = [(0.0, 0, 1.0), (0.1, 1, 1.001), (0.2, 1, 1.0)]
    assert drive(sync, arrivals) == sets(("A@1", "B@1"))


def test_three_inputs_at_different_rates() -> None:
    # A at 10 Hz, B at 2 Hz, C at 1 Hz with jitter; slop 50 ms; arrivals in stamp order.
    sync = make(inputs=3, slop=0.05, timeout=5.0)
    stamps = [(round(0.1 * k, 2), 0) for k in range(21)]
    stamps += [(0.0, 1), (0.49, 1), (0.99, 1), (1.51, 1), (2.0, 1)]
    stamps += [(0.01, 2), (1.02, 2), (1.98, 2)]
    arrivals = [(s, i, s) for s, i in sorted(stamps)]
    assert drive(sync, arrivals) == sets(
        ("A@0", "B@0", "C@0.01"),
        ("A@1", "B@0.99", "C@1.02"),
        ("A@2", "B@2", "C@1.98"),
    )
    # B@0.49 and B@1.51 have no C within 50 ms; they go out of date when a newer B is used.
    assert sync.counters.incomplete_sets == 0


def test_a_message_stamped_before_the_last_used_one_is_late() -> None:
    sync = make(slop=0.1)
    drive(sync, [(0.0, 0, 2.0), (0.1, 1, 2.0)])
    assert sync.offer(0, ns(1.0), "A@1", 0.2) is None
    assert sync.offer(0, ns(2.0), "A@2 again", 0.3) is None
    assert sync.counters.late == 2
    assert sync.pending_count() == 0


def test_timeout_returns_an_incomplete_set_only_once_due() -> None:
    sync = make(slop=0.1, timeout=2.0)
    sync.offer(0, ns(1.0), "A@1", 10.0)
    assert sync.expire(11.999) == []
    assert sync.next_deadline() == pytest.approx(12.0)
    (incomplete,) = sync.expire(12.0)
    assert label(incomplete) == ("A@1", None)
    assert incomplete.missing == (1,)
    assert not incomplete.complete
    assert sync.pending_count() == 0
    assert sync.next_deadline() is None


def test_a_silent_input_does_not_block_and_partners_time_out_together() -> None:
    # C stops after the first set: A and B messages of one instant time out as one set.
    sync = make(inputs=3, slop=0.1, timeout=1.5)
    arrivals = [
        (0.0, 0, 0.0), (0.0, 1, 0.0), (0.0, 2, 0.0),
        (1.0, 0, 1.0), (1.0, 1, 1.0),
        (2.0, 0, 2.0), (2.0, 1, 2.0),
        (3.0, 0, 3.0), (3.0, 1, 3.0),
        (3.5, 2, 3.02),  # C is back
    ]  # fmt: skip
    assert drive(sync, arrivals) == [
        ("set", ("A@0", "B@0", "C@0")),
        ("timeout", ("A@1", "B@1", None)),
        ("timeout", ("A@2", "B@2", None)),
        ("set", ("A@3", "B@3", "C@3.02")),
    ]
    assert sync.counters.complete_sets == 2
    assert sync.counters.incomplete_sets == 2


def test_a_timed_out_set_supersedes_older_messages_of_its_inputs() -> None:
    sync = make(slop=0.1, timeout=1.0)
    sync.offer(0, ns(5.0), "A@5", 0.0)
    sync.offer(0, ns(4.0), "A@4", 0.5)  # arrived later, stamped earlier
    (incomplete,) = sync.expire(1.0)
    assert label(incomplete) == ("A@5", None)
    assert sync.counters.superseded == 1
    assert sync.pending_count() == 0


def test_full_queue_discards_the_oldest_stamp() -> None:
    sync = make(slop=0.1, queue_size=3)
    for k in range(5):
        sync.offer(0, ns(float(k)), f"A@{k}", float(k))
    assert sync.counters.overflowed == 2
    assert sync.pending_count() == 3
    synced = sync.offer(1, ns(2.0), "B@2", 5.0)
    assert synced is not None and label(synced) == ("A@2", "B@2")
    assert sync.offer(1, ns(0.0), "B@0", 5.1) is None  # A@0 is gone (and B@0 is late anyway)


def test_single_input_emits_every_message() -> None:
    sync = make(inputs=1)
    assert drive(sync, [(0.0, 0, 1.0), (1.0, 0, 2.0)]) == sets(("A@1",), ("A@2",))


def test_flush_settles_everything_pending() -> None:
    sync = make(inputs=3, slop=0.1)
    drive(sync, [(0.0, 0, 1.0), (0.0, 1, 1.05), (0.1, 0, 2.0)])
    assert [label(s) for s in sync.flush()] == [("A@1", "B@1.05", None), ("A@2", None, None)]
    assert sync.pending_count() == 0


def test_synchronised_stamp_is_the_latest_of_the_set() -> None:
    sync = make(slop=1.0)
    sync.offer(0, ns(10.2), "A", 0.0)
    synced = sync.offer(1, ns(9.9), "B", 0.1)
    assert synced is not None
    assert synced.stamp_ns == ns(10.2)
    assert synced.spread_ns == ns(0.3)


@pytest.mark.parametrize(
    ("kwargs", "inputs"),
    [
        ({"slop_ns": -1, "timeout": 1.0, "queue_size": 1}, 2),
        ({"slop_ns": 0, "timeout": 0.0, "queue_size": 1}, 2),
        ({"slop_ns": 0, "timeout": 1.0, "queue_size": 0}, 2),
        ({"slop_ns": 0, "timeout": 1.0, "queue_size": 1}, 0),
    ],
)
def test_invalid_arguments_are_refused(kwargs: dict[str, float], inputs: int) -> None:
    with pytest.raises(ValueError):
        ApproximateTimeSync(inputs, **kwargs)  # type: ignore[arg-type]
