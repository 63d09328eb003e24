"""Live views of a running DC: `dc top` (rates from the metrics endpoints) and `dc tap` (records as they pass).

Both find the servers as `dc status` does (:func:`metrics_targets`): the addresses the running servers
wrote down in the runtime folder (dc_core.metrics_registry) for this ROS domain and namespace, else
the ports a parameter file configures.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dc_core.errors import DcError
from dc_core.params import url_host

# What a terminal of a laptop or an SSH session shows without wrapping; `--wide` shows everything.
WIDTH = 100


@dataclass(frozen=True)
class Target:
    """A server's metrics endpoint; ``server`` is empty when only an address was given."""

    server: str
    host: str
    port: int

    @property
    def url(self) -> str:
        return f"http://{url_host(self.host)}:{self.port}/api/v1/metrics"


def add_namespace_argument(p: argparse.ArgumentParser) -> None:
    """``--namespace`` of a command that talks to the servers of a running dc-bringup."""
    p.add_argument("--namespace", default="", help="the namespace dc-bringup was started with (--namespace)")


def add_metrics_target_arguments(p: argparse.ArgumentParser) -> None:
    """The options :func:`metrics_targets` reads: which servers `dc status` and `dc top` ask."""
    p.add_argument("--params", default="", help="only the servers of this parameter file (their ports if not running)")
    add_namespace_argument(p)
    p.add_argument("--host", default="127.0.0.1", help="with --port: the host of one server")
    p.add_argument("--port", type=int, default=None, help="one server's metrics port, instead of finding them")


def metrics_targets(
    params: str, namespace: str, host: str, port: int | None, command: str = "dc status"
) -> list[Target]:
    """The endpoints to ask: ``--port`` alone; else the servers running in this ROS domain and
    namespace (their written-down addresses), those of ``params`` only when given; else, for a server
    not found running, the port ``params`` configures (raises DcError when ``params`` is invalid and
    none runs). Empty, and said on stderr, when nothing is found."""
    from dc_core.metrics_registry import announced, domain_id_from_env, folder

    if port is not None:
        return [Target("", host, port)]
    running = announced(domain_id_from_env(), namespace)
    if not params:
        if running:
            return [Target(a.server, a.host, a.port) for a in running.values()]
        # Not a guess at the default port: another DC of the machine may hold it, and its counters
        # would be shown as this one's.
        where = folder(domain_id_from_env(), namespace)
        print(
            f"{command}: no running DC server found in {where} (is dc-bringup running, with this ROS_DOMAIN_ID "
            "and --namespace? --params F asks the ports F configures, --port P one server)",
            file=sys.stderr,
        )
        return []
    from dc_bringup.validate import metrics_endpoints, validate_params_file
    from dc_core.config import UnsetShown

    # The servers' secrets live in their service's environment, not in this shell: only addresses are read here.
    environ = UnsetShown()
    try:
        configs = validate_params_file(params, namespace, environ=environ).configs
        if environ.unset:
            print(
                f"{command}: not set in this shell, shown as unset: {', '.join(sorted(environ.unset))}", file=sys.stderr
            )
    except DcError as exc:
        if not running:
            raise
        # The servers' addresses are known without the file (which may need a secret's variable
        # that only the servers' environment has).
        print(f"{command}: {params} not read ({exc}); asking the servers running", file=sys.stderr)
        return [Target(a.server, a.host, a.port) for a in running.values()]
    targets = []
    for endpoint in metrics_endpoints(configs):
        found = running.get(endpoint.server)
        if found is not None:
            targets.append(Target(endpoint.server, found.host, found.port))
        else:
            listen = "127.0.0.1" if endpoint.listen in ("0.0.0.0", "") else endpoint.listen
            targets.append(Target(endpoint.server, listen, endpoint.port))
    if not targets:
        print(f"{command}: every server of {params} has http_server: false", file=sys.stderr)
    return targets


def fetch(target: Target, timeout: float = 5.0) -> dict[str, Any]:
    with urllib.request.urlopen(target.url, timeout=timeout) as response:
        document: dict[str, Any] = json.loads(response.read())
    return document


def server_kind(document: dict[str, Any]) -> str:
    if "groups" in document:
        return "group_server"
    if "measurements" in document:
        return "measurement_server"
    return "destination_server"


# -- dc top ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Sample:
    at: float
    documents: dict[str, dict[str, Any]]  # by server
    unreachable: dict[str, str]  # server -> why


def take_sample(targets: list[Target]) -> Sample:
    documents, unreachable = {}, {}
    for target in targets:
        name = target.server or f"{target.host}:{target.port}"
        try:
            document = fetch(target)
        except (urllib.error.URLError, OSError, ValueError) as exc:
            unreachable[name] = f"{target.url}: {exc}"
            continue
        documents[target.server or server_kind(document)] = document
    return Sample(time.monotonic(), documents, unreachable)


def _rate(now: dict[str, Any], before: dict[str, Any] | None, key: str, seconds: float) -> float | None:
    if before is None or seconds <= 0:
        return None
    a, b = now.get(key), before.get(key)
    if not isinstance(a, int | float) or not isinstance(b, int | float):
        return None
    return max(a - b, 0) / seconds


def _grew(now: dict[str, Any], before: dict[str, Any] | None, key: str) -> bool:
    return before is not None and (now.get(key) or 0) > (before.get(key) or 0)


def _measurement_state(row: dict[str, Any], before: dict[str, Any] | None) -> str:
    """What a measurement did in the interval: the thing an operator asks first (is it publishing?)."""
    if _grew(row, before, "errors"):
        return "errors"
    if _grew(row, before, "published"):
        return "publishing"
    if _grew(row, before, "gated"):
        return "gated"
    if _grew(row, before, "empty") or _grew(row, before, "invalid"):
        return "empty"
    return "waiting"


def _group_state(row: dict[str, Any], before: dict[str, Any] | None) -> str:
    if _grew(row, before, "dropped_incomplete"):
        return "dropping"
    if _grew(row, before, "published") or _grew(row, before, "published_partial"):
        return "merging"
    return "waiting"


def _num(value: Any, digits: int = 0) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _name(name: str, width: int) -> str:
    return name if len(name) <= width else name[: width - 1] + "~"


# A `dc top` column: heading, width, and its cell from (row now, row an interval ago, seconds between).
Column = tuple[str, int, Callable[[dict[str, Any], dict[str, Any] | None, float], str]]


def _rate_of(key: str) -> Callable[[dict[str, Any], dict[str, Any] | None, float], str]:
    return lambda row, was, seconds: _num(_rate(row, was, key, seconds), 2)


def _value_of(key: str, digits: int = 0) -> Callable[[dict[str, Any], dict[str, Any] | None, float], str]:
    return lambda row, was, seconds: _num(row.get(key), digits)


def _health_of(row: dict[str, Any], was: dict[str, Any] | None, seconds: float) -> str:
    health = row.get("health")
    return str(health.get("state") or "-") if isinstance(health, dict) else "-"


# (server, section of its document, title, columns), in the order records flow; each row fits WIDTH.
TOP_SECTIONS: list[tuple[str, str, str, list[Column]]] = [
    (
        "measurement_server",
        "measurements",
        "measurement",
        [
            ("state", -12, lambda row, was, seconds: _measurement_state(row, was)),
            ("rec/s", 8, _rate_of("published")),
            ("published", 11, _value_of("published")),
            ("collected", 11, _value_of("collected")),
            ("gated", 8, _value_of("gated")),
            ("errors", 8, _value_of("errors")),
            ("lost", 8, lambda row, was, seconds: _num(row.get("lost", 0))),
        ],
    ),
    (
        "group_server",
        "groups",
        "group",
        [
            ("state", -12, lambda row, was, seconds: _group_state(row, was)),
            ("rec/s", 8, _rate_of("published")),
            ("published", 11, _value_of("published")),
            ("partial", 9, _value_of("published_partial")),
            ("dropped", 9, _value_of("dropped_incomplete")),
            ("pending", 9, _value_of("pending")),
        ],
    ),
    (
        "destination_server",
        "destinations",
        "destination",
        [
            ("state", -10, _health_of),
            ("in/s", 8, _rate_of("received")),
            ("sent/s", 8, _rate_of("sent")),
            ("pending", 9, _value_of("buffered")),
            ("oldest s", 10, _value_of("oldest_pending_age_s", 1)),
            ("failed", 8, _value_of("failed")),
            ("dropped", 9, _value_of("dropped")),
            ("dead", 7, _value_of("dead_letters")),
        ],
    ),
]


def _cell(text: str, width: int) -> str:
    """Right-aligned in ``width``; a negative width: left-aligned in its absolute value."""
    return f"{text:<{-width}}" if width < 0 else f"{text:>{width}}"


def top_table(before: Sample | None, now: Sample, interval: float, header: str) -> list[str]:
    """The lines of one `dc top` view, each at most :data:`WIDTH` columns."""
    seconds = now.at - before.at if before is not None else 0.0
    lines = [header[:WIDTH]]
    old = before.documents if before is not None else {}
    for server, section, title, columns in TOP_SECTIONS:
        rows = now.documents.get(server, {}).get(section, {})
        if not isinstance(rows, dict) or not rows:
            continue
        previous = old.get(server, {}).get(section, {})
        lines += ["", f"{title:<22}" + "".join(_cell(heading, width) for heading, width, _ in columns)]
        for name, row in sorted(rows.items()):
            if isinstance(row, dict):
                was = previous.get(name) if isinstance(previous, dict) else None
                cells = "".join(_cell(value(row, was, seconds), width) for _, width, value in columns)
                lines.append(f"{_name(name, 21):<22}{cells}")
    destinations = now.documents.get("destination_server", {}).get("destinations", {})
    for name, row in sorted(destinations.items()) if isinstance(destinations, dict) else []:
        health = row.get("health") if isinstance(row, dict) else None
        if isinstance(health, dict) and health.get("state") in ("retrying", "failing"):
            lines.append(f"  {name}: {health.get('reason') or row.get('last_error') or ''}"[:WIDTH])

    for server, why in sorted(now.unreachable.items()):
        lines.append(f"{server}: unreachable ({why})"[:WIDTH])
    if not now.documents and not now.unreachable:
        lines.append("no DC server found")
    return lines


def cmd_top(args: argparse.Namespace) -> int:
    if args.interval <= 0:
        print("dc top: --interval must be above 0", file=sys.stderr)
        return 2
    try:
        targets = metrics_targets(args.params, args.namespace, args.host, args.port, "dc top")
    except DcError as exc:
        print(f"dc top: {exc}", file=sys.stderr)
        return 2
    if not targets:
        return 1
    # Clearing the screen only makes sense on a terminal; piped, each view follows the last.
    redraw = sys.stdout.isatty() and not args.once
    where = ", ".join(t.server or f"{t.host}:{t.port}" for t in targets)
    before = take_sample(targets)
    try:
        while True:
            time.sleep(args.interval)
            now = take_sample(targets)
            stamp = time.strftime("%H:%M:%S", time.gmtime())
            header = f"dc top  {stamp} UTC  every {args.interval:g} s  ({where})"
            lines = top_table(before, now, args.interval, header)
            if redraw:
                sys.stdout.write("\x1b[H\x1b[2J")
            sys.stdout.write("\n".join(lines) + "\n" + ("" if redraw else "\n"))
            sys.stdout.flush()
            before = now
            if args.once:
                return 1 if now.unreachable or not now.documents else 0
    except KeyboardInterrupt:
        return 0


def add_top_arguments(p: argparse.ArgumentParser) -> None:
    add_metrics_target_arguments(p)
    p.add_argument("--interval", type=float, default=2.0, help="seconds between views (the rates' interval)")
    p.add_argument("--once", action="store_true", help="one view after one interval, then exit (for scripts)")
    p.set_defaults(func=cmd_top)


# -- dc tap ---------------------------------------------------------------------------------------


def _filter(text: str) -> tuple[str, Any]:
    path, sep, value = text.partition("=")
    if not sep or not path:
        raise argparse.ArgumentTypeError(f"{text!r}: expected PATH=VALUE, e.g. name=uptime")
    try:
        return path, json.loads(value)
    except ValueError:
        return path, value  # a bare word: a string


def matches(record: Any, filters: list[tuple[str, Any]]) -> bool:
    """Every filter's path holds its value (a number or string written either way: 3 matches "3")."""
    from dc_core.jsonpath import PathNotFound, get_path

    for path, wanted in filters:
        try:
            found = get_path(record, path)
        except (PathNotFound, TypeError, ValueError):
            return False
        if found != wanted and str(found) != str(wanted):
            return False
    return True


def tap_topics(target: str, params: str, namespace: str) -> tuple[list[str], list[str]]:
    """(topics named by ``target`` for sure, topics to try in order when nothing says which):
    a topic name; with ``params``, a measurement, group or destination of that file (its inputs)."""
    from dc_core.topics import GROUP_TOPIC_PREFIX, MEASUREMENT_TOPIC_PREFIX, resolve_topic

    ns = namespace or "/"
    if target.startswith("/") or "/" in target:
        return [resolve_topic(target, ns)], []
    if params:
        from dc_bringup.validate import validate_params_file

        configs = validate_params_file(params, namespace).configs
        measurements = configs.get("measurement_server")
        for m in measurements.measurements if measurements is not None else []:
            if m.name == target:
                return [m.output_topic], []
        groups = configs.get("group_server")
        for g in groups.groups if groups is not None else []:
            if g.name == target:
                return [g.output], []
        destinations = configs.get("destination_server")
        for d in destinations.destinations if destinations is not None else []:
            if d.name == target:
                return list(dict.fromkeys(d.common.inputs)), []
        raise DcError(f"{params} has no measurement, group or destination named {target!r}")
    return [], [
        resolve_topic(MEASUREMENT_TOPIC_PREFIX + target, ns),
        resolve_topic(GROUP_TOPIC_PREFIX + target, ns),
        resolve_topic(target, ns),
    ]


def cmd_tap(args: argparse.Namespace) -> int:
    try:
        sure, candidates = tap_topics(args.target, args.params, args.namespace)
    except DcError as exc:
        print(f"dc tap: {exc}", file=sys.stderr)
        return 2
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from dc_core.records import MalformedRecord, parse_record
    from dc_core.stamped_cdr import read_stamped_record
    from dc_interfaces.msg import StringStamped

    rclpy.init()
    node = rclpy.create_node("dc_tap")
    try:
        # Publishers show up in the graph after discovery: wait for them, within the timeout.
        deadline = time.monotonic() + args.timeout
        topics: list[str] = []
        while True:
            if sure:
                topics = [t for t in sure if node.count_publishers(t)]
                if len(topics) == len(sure):
                    break
            else:
                topics = [t for t in candidates if node.count_publishers(t)][:1]
                if topics:
                    break
            if time.monotonic() >= deadline:
                break
            rclpy.spin_once(node, timeout_sec=0.1)
        if not topics:
            named = ", ".join(sure or candidates)
            hint = "" if sure else "; a destination's name needs --params"
            print(
                f"dc tap: no publisher on {named} after {args.timeout:g} s (is dc-bringup running, in this ROS "
                f"domain and --namespace?{hint})",
                file=sys.stderr,
            )
            return 1
        if sure and len(topics) < len(sure):
            missing = ", ".join(t for t in sure if t not in topics)
            print(f"dc tap: no publisher yet on {missing}; tapping the others", file=sys.stderr)
        print(f"dc tap: {', '.join(topics)}", file=sys.stderr)
        shown = 0

        def show(topic: str, serialised: bytes) -> None:
            nonlocal shown
            if args.count and shown >= args.count:
                return
            stamp_ns, data, _ = read_stamped_record(serialised)
            try:
                record: Any = parse_record(data)
            except MalformedRecord:
                record = data  # shown as it came: a tap is where a malformed record is looked at
            if not matches(record, args.filter):
                return
            shown += 1
            when = time.strftime("%H:%M:%S", time.gmtime(stamp_ns / 1e9)) + f".{stamp_ns % 10**9 // 10**6:03d}"
            if len(topics) > 1:
                print(f"# {topic} {when} UTC", flush=True)
            print(json.dumps(record, indent=2, ensure_ascii=False), flush=True)

        # Volatile: records as they pass from now on, not the history a late joiner would be given.
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
        for topic in topics:
            node.create_subscription(StringStamped, topic, functools.partial(show, topic), qos, raw=True)
        while not args.count or shown < args.count:
            rclpy.spin_once(node, timeout_sec=0.5)
        return 0
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `dc tap X | head` has read enough; nothing more to flush at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    finally:
        node.destroy_node()
        rclpy.shutdown()


def add_tap_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "target",
        help="a measurement or group id (its output topic), a destination name (its inputs; needs --params), "
        "or a topic",
    )
    p.add_argument("--params", default="", help="find the target in this parameter file")
    add_namespace_argument(p)
    p.add_argument(
        "--filter",
        type=_filter,
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="only records whose PATH (a /-separated key path: name, tags/0, memory/used) equals VALUE; "
        "repeat for all of them",
    )
    p.add_argument("--count", type=int, default=0, help="exit 0 after this many records (default: until Ctrl-C)")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for a publisher (exit 1 without)")
    p.set_defaults(func=cmd_tap)
