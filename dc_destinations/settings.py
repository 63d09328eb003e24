"""Delivery settings: the ``flb`` section of ``destination_server`` and per-destination options.

The key names are those of the original's Fluent Bit section so its configurations keep working;
DC's own buffer gives them their meaning (see docs/delivery.md).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from dc_core.errors import ConfigError
from dc_core.node_params import MetricsHttpParams, http_port_param
from dc_core.params import compat_param, param
from dc_destinations.links import OnlyWhenParams

WHEN_FULL_POLICIES = ("drop_oldest", "drop_newest")

_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)(i?b?)\s*$", re.IGNORECASE)
_UNITS = {"": 1, "k": 1024, "m": 1024**2, "g": 1024**3, "t": 1024**4}


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
        0, doc="Under flb.disk_budget_mb, the records of a lower retention_priority are evicted first"
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
    ``disk_budget_mb`` too (the other check of the section that needs more than one key's range)."""
    if 0 < settings.disk_budget_mb < 1:
        raise ConfigError(
            f"{path}.disk_budget_mb",
            f"a budget of {settings.disk_budget_mb:g} MB is smaller than one batch of records may be: "
            "give at least 1, or 0 for no budget",
        )
    rates = {}
    for name, text in settings.links.items():
        rate = parse_rate(str(text), f"{path}.links.{name}")
        if rate is None:
            raise ConfigError(f"{path}.links.{name}", 'expected a rate such as "125k"')
        rates[str(name)] = rate
    return rates


def check_destination_params(params: DestinationDeliveryParams, path: str, links: dict[str, str] | None = None) -> None:
    """Checks :func:`parse_params` cannot express; ``path`` is the destination's YAML path, ``links``
    the server's ``flb.links`` when known."""
    parse_size(params.storage_total_limit_size, f"{path}.storage_total_limit_size")
    parse_size(params.dead_letter_limit_size, f"{path}.dead_letter_limit_size")
    parse_rate(params.max_bytes_per_s, f"{path}.max_bytes_per_s")
    if links is not None and params.link and params.link not in links:
        raise ConfigError(
            f"{path}.link", f'no link "{params.link}" in flb.links ({", ".join(sorted(links)) or "none defined"})'
        )
