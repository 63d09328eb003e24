"""Delivery settings: the ``flb`` section of ``destination_server`` and per-destination options.

The key names are those of the original's Fluent Bit section so its configurations keep working;
DC's own buffer gives them their meaning (see docs/delivery.md).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.errors import ConfigError
from dc_core.node_params import MetricsHttpParams, http_port_param
from dc_core.params import compat_param, param
from dc_core.records import measurement_of
from dc_destinations.links import OnlyWhenParams

WHEN_FULL_POLICIES = ("drop_oldest", "drop_newest")

_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)(i?b?)\s*$", re.IGNORECASE)
_UNITS = {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3, "t": 1024**4}


def time_key_param(doc: str) -> Any:
    """A destination's ``time_key``: declared by the common parameters, and again by a plugin that reads
    it too (Kinesis' time_key_format), with one default and the original's spelling for both."""
    return param("date", aliases=("json_date_key",), doc=doc)


def _size_problem(text: str) -> str | None:
    return None if text.strip() in ("", "0") or _SIZE.match(text) else 'a size such as "64M" or a number of bytes'


@dataclass(frozen=True, kw_only=True)
class DeliveryParams(MetricsHttpParams):
    flush: float = param(1.0, minimum=0.01, doc="Seconds between two delivery rounds of a destination's queue")
    grace: float = param(1.0, minimum=0.0, doc="Seconds to keep delivering at shutdown before leaving the rest on disk")
    log_level: str = compat_param("info", "the log level is dc-bringup's --log-level")
    storage_path: str = param(
        "",
        doc="Buffer folder, owned by one destination server (default: $XDG_DATA_HOME/dc/buffer/domain-<ROS_DOMAIN_ID>/"
        "<namespace>, XDG_DATA_HOME defaulting to ~/.local/share)",
    )
    storage_sync: str = param(
        "normal",
        choices=("normal", "full"),
        doc="normal: committed records survive a process crash; full: they also survive a power cut",
    )
    storage_checksum: str = compat_param("off", "SQLite checks its own pages")
    storage_backlog_mem_limit: str = compat_param("5M", "the backlog is streamed from disk")
    scheduler_cap: float = param(2000.0, minimum=0.0, doc="Longest wait between two retries, seconds")
    scheduler_base: float = param(5.0, minimum=0.0, doc="Base of the exponential retry backoff, seconds")
    http_port: int = http_port_param(2020)
    in_storage_type: str = compat_param("filesystem", "DC always buffers on disk")
    in_storage_pause_on_chunks_overlimit: str = compat_param(
        "off", "beyond intake_queue_limit new records are dropped and counted, the intake never pauses"
    )
    intake_queue_limit: int = param(
        20000,
        minimum=1,
        doc="Records waiting in memory for the next group commit; beyond it new ones are dropped and counted",
    )
    intake_queue_limit_bytes: str = param(
        "64M",
        check=_size_problem,
        doc="Bytes of records (their JSON) waiting in memory for the next group commit; beyond it new ones are "
        'dropped and counted, as beyond intake_queue_limit ("0" or "" = records counted only)',
    )
    commit_batch_size: int = param(2000, minimum=1, doc="Most records written by one group commit")
    buffer_check_interval: float = param(
        3600.0,
        minimum=0.0,
        doc="Seconds between two integrity checks (PRAGMA quick_check) of the buffer file while running; "
        "it is also checked at start. 0 = at start only",
    )
    commit_interval: float = param(
        0.05,
        minimum=0.0,
        maximum=1.0,
        doc="Seconds a record may wait in memory so that records arriving together share one commit",
    )

    links: dict[str, str] = param(
        default_factory=dict,
        doc='Shared caps: link name -> bytes per second ("125k" for 1 Mbit/s LTE), for the destinations whose '
        "link names it",
    )
    disk_budget_mb: float = param(
        0.0,
        minimum=0.0,
        doc="Most MB of records the buffer holds for all destinations together; over it the oldest records of the "
        "lowest retention_priority are evicted and counted (0 = no budget; at least 1)",
    )
    burst_s: float = param(
        1.0, minimum=0.01, doc="Seconds of its rate a cap may send at once after a quiet spell (the burst)"
    )
    disk_budget: str = param(
        "",
        doc="Most disk the buffer's records and DC's saved files take together: a size (\"50M\") or a percentage of "
        'the buffer\'s filesystem ("10%"); over it, evicted by value and counted ("" = none; see disk_budget_mb)',
    )
    disk_free_floor: str = param(
        "",
        doc='Least free space on the buffer\'s filesystem ("5%", "1G"): below it, whoever filled the disk, DC evicts '
        'by the same rules as over disk_budget ("" = none)',
    )
    retention_priorities: dict[str, int] = param(
        default_factory=dict,
        doc="Measurement name -> retention priority of the files its records name (saved images, maps, "
        "recordings): over the budget, the lower go first (absent: 0)",
    )
    keep_run_ends: int = param(
        0,
        minimum=0,
        doc="Saved files kept to the last of their priority: the first and the last N of each measurement and run",
    )

    @property
    def intake_limit_bytes(self) -> int | None:
        """``intake_queue_limit_bytes`` in bytes; None: no byte limit."""
        return parse_size(self.intake_queue_limit_bytes, "intake_queue_limit_bytes")


@dataclass(frozen=True, kw_only=True)
class DestinationDeliveryParams:
    batch_size: int = param(500, minimum=1, doc="Most records handed to one send()")
    retry_limit: int = param(
        -1,
        minimum=-1,
        doc="Failed attempts retried before a record is dead-lettered (-1 = unlimited, 0 = no retry)",
    )
    storage_total_limit_size: str = param(
        "1G",
        doc='Most bytes of records buffered for this destination ("500M", "2G", bytes; "0" or "" = no limit)',
    )
    when_full: str = param(
        "drop_oldest",
        choices=WHEN_FULL_POLICIES,
        doc="When full: drop_oldest deletes the oldest buffered records; drop_newest refuses new ones",
    )
    dead_letter_limit_size: str = param(
        "100M",
        doc="Most bytes of dead letters kept for this destination; beyond it the oldest are deleted and counted"
        ' ("0" or "" = no limit)',
    )
    unhealthy_after: float = param(
        0.0,
        minimum=0.0,
        doc="Seconds without a successful send before this destination is reported failing"
        " (0 = destination_server's unhealthy_after)",
    )
    only_when: OnlyWhenParams = param(
        default_factory=OnlyWhenParams,
        doc="When this destination may send; outside it records wait in the buffer (docs/constrained_links.md)",
    )
    max_bytes_per_s: str = param(
        "", doc='Most bytes per second this destination sends ("125k", "1M"; "" = no cap of its own)'
    )
    retention_priority: int = param(
        0, doc="Under flb.disk_budget, the records of a lower retention_priority are evicted first"
    )
    retention_priorities: dict[str, int] = param(
        default_factory=dict,
        doc="Measurement name or input topic -> retention priority of this destination's records from it, under "
        "flb.disk_budget (absent: retention_priority)",
    )
    link: str = param("", doc="Name of the link (in flb.links) whose cap this destination shares")
    priority: int = param(
        0, doc="Order among the destinations waiting for a shared link: higher first (records before files always)"
    )


def parse_size(text: str, path: str = "") -> int | None:
    """Bytes of a size such as ``"500M"``, ``"2GiB"`` or ``"1048576"``; ``None`` means no limit."""
    if text.strip() in ("", "0"):
        return None
    match = _SIZE.match(text)
    if match is None:
        raise ConfigError(path, f'expected a size such as "500M", "2G" or a number of bytes, got "{text}"')
    number, unit, _suffix = match.groups()
    return int(float(number) * _UNITS[unit.lower()])


def parse_rate(text: str, path: str) -> float | None:
    """Bytes per second of a cap ("125k", "1M", a number); None for "" (no cap); a cap of 0 is refused."""
    if not text.strip():
        return None
    rate = parse_size(text, path)
    if rate is None or rate <= 0:
        raise ConfigError(
            path, f'a cap of "{text.strip()}" would never send: give a rate such as "125k", or "" for none'
        )
    return float(rate)


def link_rates(settings: DeliveryParams, path: str) -> dict[str, float]:
    """``flb.links`` as bytes per second; ``path`` is the ``flb`` section's YAML path. Checks
    the disk budget too (the other checks of the section that need more than one key's range)."""
    budget_limits(settings, path)
    rates = {}
    for name, text in settings.links.items():
        rate = parse_rate(str(text), f"{path}.links.{name}")
        if rate is None:
            raise ConfigError(f"{path}.links.{name}", 'expected a rate such as "125k"')
        rates[str(name)] = rate
    return rates


@dataclass(frozen=True)
class BudgetLimits:
    """The disk budget of the ``flb`` section, read: bytes or a fraction of the buffer's filesystem."""

    budget_bytes: int | None = None
    budget_fraction: float | None = None
    floor_bytes: int | None = None
    floor_fraction: float | None = None

    @property
    def active(self) -> bool:
        limits = (self.budget_bytes, self.budget_fraction, self.floor_bytes, self.floor_fraction)
        return any(v is not None for v in limits)

    def budget(self, filesystem_bytes: int) -> int | None:
        """The budget in bytes on a filesystem of ``filesystem_bytes``; None: no budget."""
        if self.budget_fraction is not None:
            return int(filesystem_bytes * self.budget_fraction)
        return self.budget_bytes

    def floor(self, filesystem_bytes: int) -> int | None:
        if self.floor_fraction is not None:
            return int(filesystem_bytes * self.floor_fraction)
        return self.floor_bytes


def _size_or_percent(text: str, path: str, what: str, zero: str) -> tuple[int | None, float | None]:
    """("50M" | "10%") as (bytes, None) or (None, fraction); ("", "") = (None, None); 0 refused."""
    text = text.strip()
    if not text:
        return None, None
    if text.endswith("%"):
        try:
            percent = float(text[:-1])
        except ValueError:
            raise ConfigError(
                path, f'expected a size such as "50M" or a percentage such as "10%", got "{text}"'
            ) from None
        if not 0 < percent < 100:
            why = zero if percent <= 0 else "is not below 100%"
            raise ConfigError(path, f'{what} of "{text}" {why}: give more than 0% and less than 100%, or "" for none')
        return None, percent / 100
    if parse_size(text, path) is None:  # "0"
        raise ConfigError(path, f'{what} of "{text}" {zero}: give a size such as "50M" or "10%", or "" for none')
    return parse_size(text, path), None


# The least disk budget: one batch of records may take as much.
_SMALLEST_BUDGET = 1024 * 1024


def _budget_too_small(path: str, given: str, least: str) -> ConfigError:
    return ConfigError(path, f"a budget of {given} is smaller than one batch of records may be: give at least {least}")


def budget_limits(settings: DeliveryParams, path: str) -> BudgetLimits:
    """``disk_budget`` (or the older ``disk_budget_mb``) and ``disk_free_floor`` of the ``flb`` section at ``path``."""
    if 0 < settings.disk_budget_mb < 1:
        raise _budget_too_small(f"{path}.disk_budget_mb", f"{settings.disk_budget_mb:g} MB", "1, or 0 for no budget")
    budget_bytes, budget_fraction = _size_or_percent(
        settings.disk_budget, f"{path}.disk_budget", "a budget", "would evict everything"
    )
    if settings.disk_budget_mb and settings.disk_budget.strip():
        raise ConfigError(f"{path}.disk_budget", "give disk_budget or disk_budget_mb, not both")
    if settings.disk_budget_mb:
        budget_bytes = int(settings.disk_budget_mb * 1024 * 1024)
    if budget_bytes is not None and budget_bytes < _SMALLEST_BUDGET:
        raise _budget_too_small(f"{path}.disk_budget", f'"{settings.disk_budget.strip()}"', "1M")
    floor_bytes, floor_fraction = _size_or_percent(
        settings.disk_free_floor, f"{path}.disk_free_floor", "a floor", "would never act"
    )
    for name in settings.retention_priorities:
        if not str(name).strip():
            raise ConfigError(f"{path}.retention_priorities", "expected measurement names as keys, got an empty one")
    return BudgetLimits(budget_bytes, budget_fraction, floor_bytes, floor_fraction)


def check_destination_params(params: DestinationDeliveryParams, path: str, links: dict[str, str] | None = None) -> None:
    """Checks :func:`parse_params` cannot express; ``path`` is the destination's YAML path, ``links``
    the server's ``flb.links`` when known."""
    parse_size(params.storage_total_limit_size, f"{path}.storage_total_limit_size")
    parse_size(params.dead_letter_limit_size, f"{path}.dead_letter_limit_size")
    parse_rate(params.max_bytes_per_s, f"{path}.max_bytes_per_s")
    for key, value in params.retention_priorities.items():
        if not str(key).strip():
            raise ConfigError(f"{path}.retention_priorities", "expected measurement names or topics as keys, got ''")
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"{path}.retention_priorities.{key}", f"expected an integer, got {value!r}")
    if links is not None and params.link and params.link not in links:
        raise ConfigError(
            f"{path}.link", f'no link "{params.link}" in flb.links ({", ".join(sorted(links)) or "none defined"})'
        )


def record_priorities(
    params: DestinationDeliveryParams,
    inputs: Sequence[str],
    path: str,
    resolve: Callable[[str], str] = str,
) -> dict[str, int]:
    """``retention_priorities`` of a destination checked against its (fully qualified) ``inputs``; a key
    naming a topic (with a ``/`` or a ``~``) resolved by ``resolve`` as the inputs are. ``path``: the
    destination's YAML path.

    The priority of a record comes from the input topic it arrived on, never from its content: any
    participant of the ROS graph can publish a record naming itself important."""
    names = {measurement_of(topic) for topic in inputs}
    out: dict[str, int] = {}
    for key, value in params.retention_priorities.items():
        where = f"{path}.retention_priorities.{key}"
        key = str(key)
        topic = "/" in key or key.startswith("~")
        resolved = resolve(key) if topic else key
        if (topic and resolved not in inputs) or (not topic and key not in names):
            raise ConfigError(
                where,
                f"{key!r} is no input topic nor measurement of this destination (its inputs: {', '.join(inputs)})",
            )
        out[resolved] = value
    return out


def priority_of(priorities: Mapping[str, int], default: int, topic: str) -> int:
    """The retention priority of a record that arrived on ``topic``: its topic's, else its measurement's,
    else ``default`` (the destination's ``retention_priority``)."""
    found = priorities.get(topic)
    if found is None:
        found = priorities.get(measurement_of(topic))
    return default if found is None else found


def by_measurement(by_topic: Mapping[str, int]) -> dict[str, int]:
    """Counts per input topic summed per measurement (:func:`measurement_of`)."""
    out: dict[str, int] = {}
    for topic, n in by_topic.items():
        name = measurement_of(topic)
        out[name] = out.get(name, 0) + n
    return out
