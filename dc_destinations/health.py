"""Whether each destination delivers: ``ok``, ``retrying`` or ``failing``, told once and shown everywhere.

A destination is ``ok`` while its sends succeed, ``retrying`` from its first failure, and ``failing``
once ``unhealthy_after`` seconds passed without a success — or at once when the failure is one that
retrying alone cannot mend (:func:`attention_needed`): a wrong password, a missing bucket or table, a
refused permission, an unknown host, a failed TLS verification. Records are still retried meanwhile
(someone may fix it); what changes is that DC stops looking healthy. Going ``failing`` is logged
once at ERROR, with the fix; coming back is logged once at INFO.

The state is read by ``/api/v1/metrics`` and ``/api/v1/health`` (and so ``dc status`` and the
dashboard), and published on :data:`HEALTH_TOPIC` for the lifecycle manager's ``is_active``
(``dc lifecycle is-active``).
"""

from __future__ import annotations

import json
import socket
import ssl
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_core.logs import Logger

OK, RETRYING, FAILING = "ok", "retrying", "failing"
DEFAULT_UNHEALTHY_AFTER_S = 60.0
# Relative: each namespace's destination_server tells its own manager.
HEALTH_TOPIC = "dc/destination_health"
HEALTH_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Causes followed down an exception's chain, at most.
_CHAIN_LIMIT = 8


def attention_needed(exc: BaseException) -> tuple[str, str] | None:
    """``(what, fix)`` when ``exc`` — or what it was raised from — is a failure retrying cannot mend.

    A destination says so with a ``fix`` (dc_core.destination.ConfigurationProblem, RejectedError);
    an unknown host (socket.gaierror) and a failed TLS verification are recognised here, once for
    every destination, even under a RetryableError raised ``from None`` (the context stays).
    """
    seen: BaseException | None = exc
    for _ in range(_CHAIN_LIMIT):
        if seen is None:
            return None
        fix = getattr(seen, "fix", "")
        if isinstance(fix, str) and fix:
            return str(exc), fix
        if isinstance(seen, socket.gaierror):
            return f"{exc} (unknown host: {seen})", "check the host name, and the robot's DNS"
        if isinstance(seen, ssl.SSLCertVerificationError):
            return (
                f"{exc} (TLS verification failed: {seen.verify_message or seen})",
                "check the server's certificate and the CA file (tls.ca_file / sslrootcert) or host name",
            )
        seen = seen.__cause__ or seen.__context__
    return None


class DestinationHealth:
    """One destination's state; fed by its sender, read by anyone. Thread-safe.

    ``clock`` (monotonic) times the failure; ``wall`` stamps it for readers on other machines.
    """

    def __init__(
        self,
        name: str,
        unhealthy_after: float,
        logger: Logger,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.name = name
        self.unhealthy_after = unhealthy_after
        self._logger = logger
        self._clock = clock
        self._wall = wall
        self._lock = threading.Lock()
        # Since when sends fail (None: the last one succeeded), on both clocks.
        self._since: float | None = None
        self._since_wall: float | None = None
        self._reason = ""
        self._fix = ""
        self._reported = False

    def succeeded(self) -> None:
        with self._lock:
            if self._since is None:
                return
            was_reported, lasted = self._reported, self._clock() - self._since
            self._since = self._since_wall = None
            self._reason = self._fix = ""
            self._reported = False
        if was_reported:
            self._logger.info(f"destination {self.name} ok again: delivered after {for_how_long(lasted)} failing")

    def failed(self, reason: str, problem: tuple[str, str] | None = None) -> None:
        """A send failed with ``reason``; ``problem``: (what, fix) from :func:`attention_needed`."""
        with self._lock:
            if self._since is None:
                self._since, self._since_wall = self._clock(), self._wall()
            if problem is not None:
                self._reason, self._fix = problem
            elif not self._fix:  # a mendable failure does not hide the problem found before it
                self._reason = reason
        self.check()

    def check(self) -> None:
        """Log the move to ``failing`` (once per failing spell); the server calls this every second."""
        with self._lock:
            if self._reported or self._state() != FAILING:
                return
            self._reported = True
            lasted, reason, fix = self._clock() - self._since_or_now(), self._reason, self._fix
        why = f"for {for_how_long(lasted)} (unhealthy_after {self.unhealthy_after:g} s)" if not fix else "at once"
        self._logger.error(
            f"destination {self.name} failing {why}: {reason} — "
            + (fix if fix else "records wait in the buffer; check that the destination is reachable")
        )

    def snapshot(self) -> dict[str, Any]:
        """``state``; while not ok: ``since`` (Unix time), ``for_s``, ``reason`` and ``fix``."""
        with self._lock:
            state = self._state()
            if state == OK:
                return {"state": OK}
            return {
                "state": state,
                "since": self._since_wall,
                "for_s": round(self._clock() - self._since_or_now(), 3),
                "reason": self._reason,
                "fix": self._fix,
            }

    def _state(self) -> str:
        if self._since is None:
            return OK
        if self._fix or self._clock() - self._since >= self.unhealthy_after:
            return FAILING
        return RETRYING

    def _since_or_now(self) -> float:
        return self._since if self._since is not None else self._clock()


def summary(states: Mapping[str, Mapping[str, Any]]) -> str:
    """The states as the JSON text published on :data:`HEALTH_TOPIC`: only what changes with the state."""
    return json.dumps(
        {
            name: {key: value for key, value in state.items() if key != "for_s"}
            for name, state in sorted(states.items())
        },
        sort_keys=True,
    )


def degraded_line(states: Mapping[str, Any], now: float) -> str:
    """``"destination pg failing for 5 min: <reason>"`` for each failing destination, ``; ``-joined
    (empty when none fails); ``states`` as :func:`summary` wrote them, ``now`` Unix time."""
    parts = []
    for name, state in sorted(states.items()):
        if not isinstance(state, dict) or state.get("state") != FAILING:
            continue
        since = state.get("since")
        lasted = f" for {for_how_long(now - since)}" if isinstance(since, int | float) else ""
        parts.append(f"destination {name} failing{lasted}: {state.get('reason') or 'no reason given'}")
    return "; ".join(parts)


def for_how_long(seconds: float) -> str:
    seconds = max(seconds, 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
