"""ROS domain IDs for the tests: none shared by two pytest-xdist workers, none reused while another is free.

Every worker gets the IDs congruent to its index modulo the number of workers, so workers running at
once never pick the same one. Within a worker they are handed out in turn: when a long session runs
out, the one used longest ago comes back, so a server still shutting down from a recent test (DDS
keeps a killed process known for a while) cannot answer a new test's requests.
"""

from __future__ import annotations

import itertools
import os
import random

# Fast DDS maps domains 0..232 to ports with its default settings.
SESSION_DOMAINS = range(1, 21)  # one per test process: in-process rclpy tests use the environment's
RUN_DOMAINS = range(21, 233)  # one per dc-bringup run, server process or isolated context

_worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
WORKER = int(_worker[2:]) if _worker[2:].isdigit() else 0
WORKERS = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
# Several test sessions at once on one machine (e.g. two checkouts): DC_TEST_DOMAIN_SLOT="k/n" gives
# session k of n the domains its workers would get if there were n times as many workers.
_slot, _, _slots = os.environ.get("DC_TEST_DOMAIN_SLOT", "0/1").partition("/")
WORKER = WORKER * int(_slots) + int(_slot)
WORKERS = WORKERS * int(_slots)


def _mine(domains: range) -> list[int]:
    return [d for d in domains if d % WORKERS == WORKER % WORKERS]


# More workers than session domains (e.g. -n 4 with DC_TEST_DOMAIN_SLOT=k/9): a worker without one
# takes its first run domain, which its runs then never use.
_SESSION_DOMAINS = _mine(SESSION_DOMAINS) or _mine(RUN_DOMAINS)[:1]


def _in_turn() -> itertools.cycle[int]:
    mine = [d for d in _mine(RUN_DOMAINS) if d not in _SESSION_DOMAINS]
    start = random.randrange(len(mine))  # two sessions one after the other start at different places
    return itertools.cycle(mine[start:] + mine[:start])


_next_run_domain = _in_turn()


def session_domain_id() -> int:
    return random.choice(_SESSION_DOMAINS)


def fresh_domain_id() -> int:
    """A domain no other worker uses, and the one this worker used longest ago."""
    return next(_next_run_domain)
