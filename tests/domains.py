"""ROS domain IDs for the tests: none shared by two runs of one process, nor by two pytest-xdist workers.

Every worker gets the IDs congruent to its index modulo the number of workers, so workers running
at once can pick at random without asking each other.
"""

from __future__ import annotations

import os
import random

# Fast DDS maps domains 0..232 to ports with its default settings.
SESSION_DOMAINS = range(1, 101)  # one per test process: in-process rclpy tests use the environment's
RUN_DOMAINS = range(101, 233)  # one per dc-bringup run, server process or isolated context

_worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
WORKER = int(_worker[2:]) if _worker[2:].isdigit() else 0
WORKERS = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
_used: set[int] = set()


def _mine(domains: range) -> list[int]:
    return [d for d in domains if d % WORKERS == WORKER % WORKERS]


def session_domain_id() -> int:
    return random.choice(_mine(SESSION_DOMAINS))


def fresh_domain_id() -> int:
    """A domain no other run of this test session uses (while any is left)."""
    free = [d for d in _mine(RUN_DOMAINS) if d not in _used]
    if not free:  # more runs than domains: reuse, leftovers of old runs are long gone
        _used.clear()
        free = _mine(RUN_DOMAINS)
    candidate = random.choice(free)
    _used.add(candidate)
    return candidate
