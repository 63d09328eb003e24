"""Parameters every DC server has at its top level, declared once for the three of them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dc_core.params import param

DEFAULT_HEARTBEAT_PERIOD_S = 1.0
DEFAULT_DIAGNOSTICS_PERIOD_S = 1.0
# measurement, group and image servers: at 1,000 forwarded records/s 0.03 s cost a sixth less CPU per
# record than 0.01 s, while a timer due meanwhile waits 30 ms at most (docs/performance.md).
DEFAULT_RECORD_LINGER_S = 0.03


def record_linger_param(default: float) -> Any:
    """The ``record_linger`` parameter, ``default`` seconds unless the server says otherwise."""
    return param(
        default,
        minimum=0.0,
        maximum=0.5,
        doc="While messages flow, seconds the server lets them gather after taking some, so that one wake-up "
        "takes many (0: wake for each); it delays records and, meanwhile, timers and requests by that much at most",
    )


@dataclass(frozen=True, kw_only=True)
class ServerNodeParams:
    use_sim_time: bool = param(
        False,
        doc="Follow the /clock topic (a bag, a simulator) instead of the system clock: record dates, polling "
        "intervals, TF lookups (dc-bringup --use-sim-time sets it for every server)",
    )
    # One a second keeps idle cost low and is ten beats within dc-bringup's default --bond-timeout.
    heartbeat_period: float = param(
        DEFAULT_HEARTBEAT_PERIOD_S, minimum=0.05, doc="Seconds between heartbeats to the lifecycle manager"
    )
    record_linger: float = record_linger_param(DEFAULT_RECORD_LINGER_S)
    # One a second is what diagnostic_updater publishes at by default.
    diagnostics_period: float = param(
        DEFAULT_DIAGNOSTICS_PERIOD_S,
        minimum=0.0,
        doc="Seconds between the server's statuses on /diagnostics (docs/diagnostics.md; 0: none published)",
    )


def http_port_param(default: int) -> Any:
    """The ``http_port`` parameter of a server whose metrics listen on ``default`` unless told otherwise."""
    return param(default, minimum=0, maximum=65535, doc="Port of the metrics HTTP server (0: any free one)")


@dataclass(frozen=True, kw_only=True)
class MetricsHttpParams:
    """The metrics HTTP server of a server: a subclass sets its own default ``http_port``."""

    # On by default (loopback only) so that `dc status` and `dc top` work on any job without edits.
    http_server: bool = param(
        True, doc="Serve health and counters over HTTP (JSON and Prometheus) while active, on loopback by default"
    )
    http_listen: str = param("127.0.0.1", doc="Address of the metrics HTTP server (loopback by default)")
    http_port: int = http_port_param(0)
