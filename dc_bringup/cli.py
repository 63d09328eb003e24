"""The `dc` command: list plugins, publish a record, validate a configuration, inspect delivery."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import textwrap
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from typing import Any, cast

from dc_core.errors import DcError
from dc_core.metrics_document import per_measurement
from dc_core.params import describe_params, url_host
from dc_core.plugins import GROUPS, describe, list_plugins, load_plugin


def cmd_list_plugins(args: argparse.Namespace) -> int:
    kinds = [args.kind] if args.kind else list(GROUPS)
    for kind in kinds:
        print(f"{kind}:")
        for info in list_plugins(kind):
            try:
                cls = load_plugin(kind, info.name)
                text = describe(cls)
            except DcError as exc:
                cls, text = None, f"(cannot load: {exc})"
            origin = "" if info.distribution == "ros2-dc" else f"  [{info.distribution}]"
            print(f"  {info.name:<36} {text}{origin}")
            if args.params and cls is not None:
                for p in describe_params(cast(Any, cls).Params):
                    default = "required" if p.required else f"default {json.dumps(p.default)}"
                    print(f"      {p.name} ({p.type_name}, {default}): {p.doc}")
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    from dc_bringup.launcher import dc_namespace
    from dc_bringup.validate import check

    report, error = check(args.params_file, dc_namespace(args), args.ros_args)
    if report is None:
        print(f"invalid: {error}", file=sys.stderr)
        return 2
    for note in report.notes:
        print(note, file=sys.stderr)
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    print(f"valid: {', '.join(report.servers)}")
    return 0


def cmd_new_plugin(args: argparse.Namespace) -> int:
    from dc_bringup.new_plugin import main

    return main(args.kind, args.name, args.dir)


def cmd_check_plugin(args: argparse.Namespace) -> int:
    from dc_bringup.plugin_contract import main

    return main(args.names)


def _records_to_publish(args: argparse.Namespace) -> list[str] | None:
    """The records `dc pub` sends: its argument, or with "-" the JSON lines of stdin (blank lines
    skipped). None, said why, when any of them is not what DC's servers carry: then none is sent,
    not the ones before the bad line."""
    from dc_core.records import MalformedRecord, parse_record

    if args.json == "-":
        if args.count != 1:
            print("dc pub: --count repeats one record; with - (records from stdin) leave it out", file=sys.stderr)
            return None
        lines = [(number, line.strip()) for number, line in enumerate(sys.stdin, 1) if line.strip()]
    else:
        lines = [(0, args.json)]
    for number, text in lines:
        try:
            parse_record(text)
        except MalformedRecord as exc:  # what DC's servers would count as malformed is not sent at all
            where = f" (stdin line {number})" if number else ""
            print(f"dc pub: refused, not JSON that DC carries{where}: {exc}", file=sys.stderr)
            return None
    if not lines:
        print("dc pub: no record on stdin", file=sys.stderr)
        return None
    return [text for _, text in lines]


def cmd_pub(args: argparse.Namespace) -> int:
    records = _records_to_publish(args)
    if records is None:
        return 2
    if args.json == "-":
        args.count = len(records)
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from dc_core.topics import ros_namespace, ros_topic, topic_problem
    from dc_interfaces.msg import StringStamped

    problem = topic_problem(args.topic)
    if problem is not None:
        print(f"dc pub: {args.topic!r}: {problem}", file=sys.stderr)
        return 2
    topic = ros_topic(args.topic)
    if topic != args.topic:
        print(f"dc pub: {args.topic!r} is not a valid ROS 2 topic name; publishing on {topic!r}", file=sys.stderr)
    args.topic = topic
    rclpy.init()
    node = rclpy.create_node("dc_pub", namespace=ros_namespace(args.namespace))
    qos = QoSProfile(
        depth=max(args.count, 10), reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
    )
    publisher = node.create_publisher(StringStamped, args.topic, qos)
    resolved = publisher.topic_name  # with --namespace, where a relative name went
    sent = 0
    unacknowledged = False
    try:
        deadline = time.monotonic() + (0 if args.no_wait else args.wait_matched)
        while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        if publisher.get_subscription_count() == 0 and not args.no_wait:
            # Once this process exits, a record nobody took is gone: "published" would be a lie.
            print(
                f"dc pub: nobody subscribes to {resolved} (waited {args.wait_matched:g} s); nothing published"
                " (--no-wait publishes anyway)",
                file=sys.stderr,
            )
            return 3
        while args.count == 0 or sent < args.count:
            msg = StringStamped()
            msg.header.stamp = node.get_clock().now().to_msg()
            msg.data = records[sent % len(records)]
            msg.group_key = args.group_key
            publisher.publish(msg)
            sent += 1
            if args.count and sent >= args.count:
                break
            rclpy.spin_once(node, timeout_sec=1.0 / args.rate if args.rate > 0 else 0)
        # Records a subscriber has not acknowledged are gone once this process exits.
        if not publisher.wait_for_all_acked(Duration(seconds=args.linger)):
            print(
                f"dc pub: a subscriber of {args.topic} had not acknowledged every record after {args.linger} s;"
                " it may miss the last ones",
                file=sys.stderr,
            )
            unacknowledged = True
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.shutdown()
    print(f"published {sent} record(s) on {resolved}")
    return 1 if unacknowledged else 0


def _get_json(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.loads(response.read())


def _status_targets(args: argparse.Namespace) -> list[tuple[str, str, int]]:
    """(server, host, port) to ask: --port; else the running servers (of --params when given)."""
    from dc_bringup.live import metrics_targets

    return [(t.server, t.host, t.port) for t in metrics_targets(args.params, args.namespace, args.host, args.port)]


STATUS_COLUMNS = [
    ("health_state", "health"),  # ok, retrying, failing: see _with_ages
    ("received", "received"),
    ("buffered", "buffered"),
    ("buffered_bytes", "bytes"),
    ("sent", "sent"),
    ("retried", "retried"),
    ("failed", "failed"),
    ("dropped", "dropped"),
    ("evicted", "evicted"),  # by the disk budget
    ("files_evicted", "files evicted"),  # saved files it carries, evicted before it had them
    ("malformed", "malformed"),
    ("dead_lettered", "dead-lettered"),
    ("dead_letters", "dead now"),
    ("dead_letters_dropped", "dead dropped"),
    ("salvaged", "salvaged"),  # read back from a damaged buffer file
    ("lost_to_damage", "lost dmg"),
    ("oldest_pending_age_s", "oldest s"),
    ("last_delivery_age_s", "sent s ago"),  # from last_delivery, see _with_ages
]


# What `dc status` shows within 100 columns; `--wide` shows every column above.
STATUS_COLUMNS_NARROW = [
    ("health_state", "health"),
    ("received", "received"),
    ("sent", "sent"),
    ("buffered", "pending"),
    ("oldest_pending_age_s", "oldest s"),
    ("failed", "failed"),
    ("dropped", "dropped"),
    ("dead_letters", "dead"),
]


GROUP_COLUMNS = [
    ("published", "published"),
    ("published_partial", "partial"),
    ("dropped_incomplete", "dropped"),
    ("superseded", "superseded"),
    ("late", "late"),
    ("overflowed", "overflowed"),
    ("renamed_keys", "renamed"),
    ("pending", "pending"),
]


GROUP_COLUMNS_NARROW = [c for c in GROUP_COLUMNS if c[0] not in ("overflowed", "renamed_keys")]


MEASUREMENT_COLUMNS = [
    ("collected", "collected"),
    ("published", "published"),
    ("gated", "gated"),
    ("empty", "empty"),
    ("invalid", "invalid"),
    ("errors", "errors"),
    ("overrun", "overrun"),
    ("malformed", "malformed"),
    ("lost", "lost"),
    ("replaced", "replaced"),
]


MEASUREMENT_COLUMNS_NARROW = [c for c in MEASUREMENT_COLUMNS if c[0] not in ("empty", "invalid", "replaced")]


def cmd_status(args: argparse.Namespace) -> int:
    try:
        targets = _status_targets(args)
    except DcError as exc:
        print(f"dc status: {exc}", file=sys.stderr)
        return 2
    if not targets:
        return 1
    documents: dict[str, Any] = {}
    unreachable = False
    for server, host, port in targets:
        url = f"http://{url_host(host)}:{port}/api/v1/metrics"
        try:
            documents[server] = _get_json(url)
        except (urllib.error.URLError, OSError) as exc:
            print(f"dc status: cannot reach {server or 'a DC server'} at {url}: {exc} (is it active?)", file=sys.stderr)
            unreachable = True
    if args.json:
        # --port: that server's document; else {server: document}, for every server found.
        if documents:
            print(json.dumps(documents.get("", documents), indent=2))
        return 1 if unreachable else 0
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        for metrics in documents.values():
            if "groups" in metrics:
                _print_groups(metrics, args.wide)
            elif "measurements" in metrics:
                columns = MEASUREMENT_COLUMNS if args.wide else MEASUREMENT_COLUMNS_NARROW
                _print_table("measurement", columns, metrics["measurements"], wide=args.wide)
            else:
                _print_delivery(metrics, args.wide)
            _print_threads(metrics)
    for line in out.getvalue().splitlines():
        # The narrow view's tables fit; a long free-text line wraps rather than widen the terminal.
        print(
            line
            if args.wide or len(line) <= STATUS_WIDTH
            else textwrap.fill(line, STATUS_WIDTH, subsequent_indent="  ")
        )
    return 1 if unreachable else 0


STATUS_WIDTH = 100


def _print_table(
    title: str, columns: list[tuple[str, str]], rows: dict[str, Any], text_column: str = "", wide: bool = True
) -> None:
    """One row per name; ``text_column``, a free-text key, goes last and unaligned (narrow: on a line
    of its own under the row, when not empty); narrow, a long name is cut to fit."""
    widths = [max(len(heading), 8) + 2 for _, heading in columns]
    header = f"{title:<20}" + "".join(f"{t:>{w}}" for (_, t), w in zip(columns, widths, strict=True))
    print(header + (f"  {text_column.replace('_', ' ')}" if text_column and wide else ""))
    for name, row in sorted(rows.items()):
        if not isinstance(row, dict):
            continue
        cells = "".join(f"{_cell(row.get(k)):>{w}}" for (k, _), w in zip(columns, widths, strict=True))
        shown = name if wide or len(name) < 20 else name[:18] + "~"
        text = row.get(text_column) or "" if text_column else ""
        print(f"{shown:<20}{cells}" + (f"  {text}" if text_column and wide else ""))
        if text and not wide:
            print(f"  {text_column.replace('_', ' ')}: {text}")


def _print_saved_files(saved: Any) -> None:
    """The saved files under the disk budget, per measurement (dc_destinations.saved_files)."""
    if not isinstance(saved, dict):
        return
    print(f"saved files under the disk budget: {saved.get('files')} files, {_cell(saved.get('bytes'))} bytes")
    for name, c in sorted((saved.get("measurements") or {}).items()):
        print(
            f"  {name} (retention_priority {c.get('retention_priority')}): produced {c.get('produced')}, "
            f"delivered {c.get('delivered')}, evicted {c.get('evicted')} ({c.get('evicted_unsent')} unsent), "
            f"kept {c.get('kept')} ({_cell(c.get('kept_bytes'))} bytes)"
        )


def _of_measurements(values: dict[str, Any], counter: str) -> str:
    """`` (records of camera 100, robot 20)``: ``counter`` per measurement, as the metrics give it."""
    of = per_measurement(values, counter)
    return " (records of " + ", ".join(f"{m} {_cell(n)}" for m, n in of) + ")" if of else ""


def _print_delivery(metrics: dict[str, Any], wide: bool = True) -> None:
    destinations = metrics.get("destinations", {})
    now = time.time()
    rows = {
        name: _with_ages(values, now) if isinstance(values, dict) else values for name, values in destinations.items()
    }
    columns = STATUS_COLUMNS if wide else STATUS_COLUMNS_NARROW
    _print_table("destination", columns, rows, text_column="last_error", wide=wide)
    for name, values in sorted(destinations.items()):
        health = values.get("health") if isinstance(values, dict) else None
        if isinstance(health, dict) and health.get("state") in ("failing", "retrying"):
            lasted = health.get("for_s")
            how_long = f" for {_cell(float(lasted))} s" if isinstance(lasted, int | float) else ""
            fix = f" — {health['fix']}" if health.get("fix") else ""
            print(f"destination {name} {str(health['state']).upper()}{how_long}: {health.get('reason')}{fix}")
        elif isinstance(values, dict) and values.get("held"):
            print(f"destination {name} {values['held']} (only_when; docs/constrained_links.md)")
        if isinstance(values, dict) and (values.get("evicted") or values.get("files_evicted")):
            print(
                f"destination {name}: {values.get('evicted') or 0} records and {values.get('files_evicted') or 0} "
                f"saved files evicted unsent by the disk budget{_of_measurements(values, 'evicted')}"
            )
        if isinstance(values, dict) and values.get("dropped"):
            print(
                f"destination {name}: {values['dropped']} records dropped by its size limit "
                f"(storage_total_limit_size) or a full intake{_of_measurements(values, 'dropped')}"
            )
    for name, values in sorted(destinations.items()):
        own = values.get("plugin") if isinstance(values, dict) else None
        if own:
            print(f"{name} (its own counters): " + ", ".join(f"{k} {_cell(v)}" for k, v in sorted(own.items())))
    buffer = metrics.get("buffer")
    if isinstance(buffer, dict):
        print(
            f"buffer: {buffer.get('path')} (storage_sync {buffer.get('storage_sync')}), "
            f"awaiting commit {buffer.get('intake_pending')}, corrupt files set aside {buffer.get('quarantined')}"
        )
        if buffer.get("buffer_damaged"):
            print(f"buffer: DAMAGED (integrity check: {buffer.get('last_check_result')}); restart to salvage it")
        elif buffer.get("last_check_time") is not None:
            ago = time.time() - float(buffer["last_check_time"])
            print(f"buffer: last integrity check {ago:.0f} s ago: {buffer.get('last_check_result')}")
        if buffer.get("salvaging"):
            print(f"buffer: salvaging the damaged file {buffer['salvaging']} (its records join their queues)")
        if buffer.get("lost_to_damage_unknown"):
            print(f"buffer: {buffer['lost_to_damage_unknown']} records lost to damage, destination unreadable")
        if buffer.get("commit_error"):
            print(
                f"buffer: COMMITS FAILING for {_cell(buffer.get('commit_failing_s'))} s, records wait in memory: "
                f"{buffer['commit_error']}"
            )
    _print_saved_files(metrics.get("saved_files"))
    account = metrics.get("disk_budget")
    if isinstance(account, dict):
        over = f", left over it by {account.get('checks_left_over')} checks" if account.get("checks_left_over") else ""
        if account.get("checks_failed"):
            over += f"; {account['checks_failed']} checks FAILED, see the log"
        print(
            f"disk budget: {_cell(account.get('held'))} of {_cell(account.get('budget'))} bytes held "
            f"(records waiting + saved files; at most {_cell(account.get('most_held'))}{over})"
        )
    for section, values in sorted(metrics.items()):
        if section not in ("destinations", "buffer", "threads", "saved_files") and isinstance(values, dict):
            flat = ", ".join(f"{k} {_cell(v)}" for k, v in values.items() if not isinstance(v, dict))
            if flat:  # a section of per-topic tables (hop) has no line of its own: --json shows it
                print(f"{section}: {flat}")
    unrouted = metrics.get("intake", {}).get("unrouted", {})
    for topic, reasons in sorted(unrouted.items()) if isinstance(unrouted, dict) else []:
        for reason, count in sorted(reasons.items()):
            print(f"unrouted: {count} on {topic}: {reason}")
    untrusted = metrics.get("intake", {}).get("untrusted_tags", {})
    for topic, destinations in sorted(untrusted.items()) if isinstance(untrusted, dict) else []:
        for name, count in sorted(destinations.items()):
            print(f"untrusted tags: {count} on {topic} kept from {name} (a publisher there is not DC's)")
    hop = metrics.get("hop", {})
    for topic, counts in sorted(hop.items()) if isinstance(hop, dict) else []:
        if not isinstance(counts, dict) or not (counts.get("missing") or counts.get("missing_lifetime")):
            continue
        ended = counts.get("writers_ended")
        missing = counts.get("missing") or 0
        earlier = (counts.get("missing_lifetime") or 0) - missing
        print(
            f"lost before destination_server: {missing} on {topic} (missing, {counts.get('gaps')} gaps"
            + (f"; {ended} publisher(s) ended holding records" if ended else "")
            + ")"
            + (f"; {earlier} more counted by earlier runs on this buffer" if earlier else "")
        )


def _print_threads(metrics: dict[str, Any]) -> None:
    """The server's thread failures (dc_core.supervision), when any thread died."""
    threads = metrics.get("threads")
    if isinstance(threads, dict) and threads.get("thread_failures"):
        print(f"threads: {threads['thread_failures']} died, the server is unhealthy: {threads.get('unhealthy')}")


def _with_ages(values: dict[str, Any], now: float) -> dict[str, Any]:
    """A destination's row with its wall-clock times as ages: at a glance, is delivery moving?"""
    row = dict(values)
    health = row.get("health")
    row["health_state"] = health.get("state") if isinstance(health, dict) else None
    if row["health_state"] == "ok" and row.get("held"):
        row["health_state"] = "held"  # by its only_when: the reason is printed under the table
    delivered, failed = row.get("last_delivery"), row.get("last_error_time")
    if isinstance(delivered, int | float):
        row["last_delivery_age_s"] = max(now - delivered, 0.0)
    if row.get("last_error") and isinstance(failed, int | float):
        row["last_error"] = f"{max(now - failed, 0.0):.0f} s ago: {row['last_error']}"
    return row


def _print_groups(metrics: dict[str, Any], wide: bool = True) -> None:
    _print_table("group", GROUP_COLUMNS if wide else GROUP_COLUMNS_NARROW, metrics.get("groups", {}), wide=wide)
    malformed = {topic: v.get("malformed", 0) for topic, v in metrics.get("inputs", {}).items() if isinstance(v, dict)}
    if any(malformed.values()):
        print("malformed inputs: " + ", ".join(f"{topic} {n}" for topic, n in sorted(malformed.items()) if n))


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.1f}"
    return str(value)


def cmd_buffer(args: argparse.Namespace) -> int:
    from dc_destinations import buffer_admin

    run: Any = getattr(buffer_admin, "run_cli", None)
    if run is None:
        print("dc buffer: not available in this version", file=sys.stderr)
        return 1
    code: int = run(args)
    return code


def cmd_replay(args: argparse.Namespace) -> int:

    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from dc_bringup.replay import ReplayError, ReplayOptions, replay, topics_argument, wait_for_argument

    if args.rate <= 0:
        print("dc replay: --rate must be above 0", file=sys.stderr)
        return 2
    from dc_core.signals import stop_on_signals

    stop = stop_on_signals()  # handlers that take no lock (dc_core.signals)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    try:
        options = ReplayOptions(
            rate=args.rate,
            loop=args.loop,
            topics=topics_argument(args.topics),
            clock=not args.no_clock,
            delay_s=args.delay,
            wait_for=wait_for_argument(args.wait_for),
        )
        replay(args.bag, options, stop)
    except ReplayError as exc:
        print(f"dc replay: {exc}", file=sys.stderr)
        return 2
    finally:
        rclpy.shutdown()
    return 0


# `dc lifecycle is-active`: the servers are active but a destination is failing (0: active and
# healthy, 1: not active, 2: no manager or no answer).
EXIT_DEGRADED = 3
LIFECYCLE_COMMANDS = ("startup", "pause", "resume", "reset", "shutdown", "is-active")


def _in_namespace(namespace: str, name: str) -> str:
    """The relative ``name`` in the namespace dc-bringup was started with (--namespace): ``/robot1/name``,
    or ``/name`` in none."""
    from dc_core.topics import ros_namespace

    return f"{ros_namespace(namespace).rstrip('/')}/{name}"


def _call_service(node: Any, client: Any, request: Any, timeout: float, asked: str, missing: str) -> Any | None:
    """The answer of ``client``'s service, waited for at most ``timeout`` seconds to appear and as long to
    answer; None once stderr said why not: ``missing`` when no one offers the service, else "``asked`` did
    not answer" (``asked``: ``dc trigger: /dc/recorder/x/trigger``)."""
    import rclpy

    if not client.wait_for_service(timeout_sec=timeout):
        print(missing, file=sys.stderr)
        return None
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if not future.done():
        print(f"{asked} did not answer in {timeout:g} s", file=sys.stderr)
        return None
    return future.result()


def cmd_lifecycle(args: argparse.Namespace) -> int:
    """Ask dc-bringup's lifecycle manager (its manage_nodes and is_active services)."""
    import rclpy
    from dc_lifecycle_interfaces.srv import ManageLifecycleNodes
    from std_srvs.srv import Trigger

    from dc_bringup.manager import DEGRADED_PREFIX, NODE_NAME

    manager = _in_namespace(args.namespace, NODE_NAME)
    rclpy.init()
    node = rclpy.create_node("dc_lifecycle")
    try:
        if args.command_name == "is-active":
            client, request = node.create_client(Trigger, f"{manager}/is_active"), Trigger.Request()
        else:
            client = node.create_client(ManageLifecycleNodes, f"{manager}/manage_nodes")
            request = ManageLifecycleNodes.Request()
            request.command = getattr(ManageLifecycleNodes.Request, args.command_name.upper())
        response = _call_service(
            node,
            client,
            request,
            args.timeout,
            f"dc lifecycle: {manager}",
            f"dc lifecycle: no lifecycle manager at {manager} (is dc-bringup running?)",
        )
        if response is None:
            return 2
        failure = ""
        if args.command_name != "is-active" and not response.success:
            failure = _last_failure(node, manager, args.timeout)
    finally:
        node.destroy_node()
        rclpy.shutdown()
    if failure:
        # One line naming the servers and what each failed at.
        print(f"{args.command_name}: failed: {failure} (see dc-bringup log)")
        return 1
    if args.command_name == "is-active":
        if response.success and response.message.startswith(DEGRADED_PREFIX):
            print(response.message)
            return EXIT_DEGRADED
        print(f"{'active' if response.success else 'not active'}: {response.message}")
    else:
        print(f"{args.command_name}: {'done' if response.success else 'failed (see dc-bringup log)'}")
    return 0 if response.success else 1


def cmd_trigger(args: argparse.Namespace) -> int:
    """Trigger a Recorder measurement: its service without a reason (the answer says what came of it), its
    reason topic with one (std_msgs/String, delivered once acknowledged; the outcome is in its log and counters)."""
    import rclpy
    from rclpy.duration import Duration
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    name = _in_namespace(args.namespace, f"dc/recorder/{args.name}/trigger")
    rclpy.init()
    node = rclpy.create_node("dc_trigger")
    try:
        if args.reason is None:
            client = node.create_client(Trigger, name)
            response = _call_service(
                node,
                client,
                Trigger.Request(),
                args.timeout,
                f"dc trigger: {name}",
                f"dc trigger: no recorder answers at {name} (is dc-bringup running it?)",
            )
            if response is None:
                return 2
            print(f"{args.name}: {response.message}")
            return 0 if response.success else 1
        publisher = node.create_publisher(String, name, QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        deadline = time.monotonic() + args.timeout
        while not publisher.get_subscription_count():
            if time.monotonic() > deadline:
                print(f"dc trigger: no recorder listens on {name} (is dc-bringup running it?)", file=sys.stderr)
                return 2
            time.sleep(0.05)
        publisher.publish(String(data=args.reason))
        if not publisher.wait_for_all_acked(Duration(seconds=args.timeout)):
            print(f"dc trigger: {name} did not acknowledge the reason in {args.timeout:g} s", file=sys.stderr)
            return 2
        print(f"{args.name}: triggered ({args.reason})")
        return 0
    finally:
        node.destroy_node()
        rclpy.shutdown()


def _last_failure(node: Any, manager: str, timeout: float) -> str:
    """What the manager's last command failed at, as its is_active tells it ("" if it does not)."""
    import rclpy
    from std_srvs.srv import Trigger

    from dc_bringup.manager import FAILED_PREFIX

    future = node.create_client(Trigger, f"{manager}/is_active").call_async(Trigger.Request())
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if not future.done():
        return ""
    return str(future.result().message).partition(FAILED_PREFIX)[2]


def cmd_servers(args: argparse.Namespace) -> int:
    from dc_bringup.local_servers.run import SERVER_NAMES, main

    unknown = [n for n in args.names if n not in SERVER_NAMES]
    if unknown:
        print(f"dc servers: unknown server(s) {', '.join(unknown)} (known: {', '.join(SERVER_NAMES)})", file=sys.stderr)
        return 2
    return main(args)


def cmd_dashboard(args: argparse.Namespace) -> int:
    from dc_dashboard.cli import run

    return run(args, params_metrics=_metrics_urls)


def _metrics_urls(params: str) -> list[tuple[str, str]]:
    """(server, URL) of the destination server of the parameter file, where it runs (else the port the
    file configures): the dashboard's Health page reads delivery, the other servers' endpoints have none."""
    from dc_bringup.live import metrics_targets

    targets = metrics_targets(params, "", "127.0.0.1", None, "dc dashboard")
    return [(t.server, t.url) for t in targets if t.server == "destination_server"]


def cmd_ingest(args: argparse.Namespace) -> int:
    """The fleet's ingest worker (dc_destinations.ingest): a JetStream consumer into DC's destinations."""
    import logging
    from pathlib import Path

    from dc_core.config import load_params_file
    from dc_core.logs import SeverityLogger
    from dc_destinations.config import parse_destination_server
    from dc_destinations.ingest import (
        Ingest,
        IngestOptions,
        configure_destinations,
        connect_options_from_env,
        run_ingest,
    )

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logger = SeverityLogger(logging.getLogger("dc.ingest"))
    try:
        section = load_params_file(args.params).get("destination_server", {})
        config = parse_destination_server(section)
        destinations = configure_destinations(config)
    except DcError as exc:
        print(f"dc ingest: {exc}", file=sys.stderr)
        return 2
    if args.handback_delay < 0:
        print("dc ingest: --handback-delay must be 0 or more", file=sys.stderr)
        return 2
    options = IngestOptions(
        servers=[u for s in args.servers for u in s.split(",") if u] or ["nats://127.0.0.1:4222"],
        stream=args.stream,
        consumer=args.consumer,
        filter=args.filter,
        batch=args.batch,
        ack_wait=args.ack_wait,
        max_in_flight=args.max_in_flight,
        handback_delay=args.handback_delay,
        connect=connect_options_from_env(),
    )
    try:
        run_ingest(Ingest(config, destinations, options, Path(args.storage_path), logger))
    except DcError as exc:  # the stream or the hand-back bucket cannot be used: said once, no traceback
        print(f"dc ingest: {exc}", file=sys.stderr)
        return 2
    finally:
        for destination in destinations.values():
            destination.on_cleanup()
    return 0


def cmd_reconcile(args: argparse.Namespace) -> int:
    from dc_bringup.reconcile import run

    return run(args)


def cmd_demo(args: argparse.Namespace) -> int:
    from dc_bringup.demo import main

    if (args.duration is not None and args.duration <= 0) or args.rate <= 0:
        print("dc demo: --duration and --rate must be above 0", file=sys.stderr)
        return 2
    return main(args)


def build_parser() -> argparse.ArgumentParser:
    from dc_bringup.live import (
        add_metrics_target_arguments,
        add_namespace_argument,
        add_tap_arguments,
        add_top_arguments,
    )

    parser = argparse.ArgumentParser(prog="dc", description="DC robot data collection: tools")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("list-plugins", help="installed plugins, built-in and third-party")
    p.add_argument("kind", nargs="?", choices=list(GROUPS))
    p.add_argument("--params", action="store_true", help="also list each plugin's parameters")
    p.set_defaults(func=cmd_list_plugins)

    p = sub.add_parser("validate", help="check a parameter file without running it")
    p.add_argument("params_file")
    p.add_argument(
        "--namespace", default="", help="check it as dc-bringup --namespace reads it (topic names in the namespace)"
    )
    p.set_defaults(func=cmd_validate)
    p.epilog = (
        "--ros-args ... (last, or ended by --): checked as dc-bringup reads them: -p and --params-file over the "
        "file's parameters, -r __ns:=/NS as --namespace, -r remaps of the robot's topics"
    )

    p = sub.add_parser(
        "check", help="preflight: validate, probe every destination, collect each measurement once, judge conditions"
    )
    p.add_argument("params_file")
    p.add_argument("--namespace", default="", help="check it as dc-bringup --namespace reads it")
    p.add_argument("--write-test", action="store_true", help="also send one test record to every destination")
    from dc_bringup.preflight import cmd_check

    p.set_defaults(func=cmd_check)

    p = sub.add_parser("new-plugin", help="a new plugin package (or a plugin added to one) that passes check-plugin")
    p.add_argument("kind", choices=["measurement", "condition", "destination"])
    p.add_argument("name", help="PACKAGE/Class, the plugin type written in YAML (my_robot_dc/Battery)")
    p.add_argument("--dir", default=".", help="where the package's folder is (or is made): DIR/<package-with-dashes>")
    p.set_defaults(func=cmd_new_plugin)

    p = sub.add_parser("check-plugin", help="DC's plugin contract on installed plugins, DC's own or not")
    p.add_argument("names", nargs="+", metavar="NAME", help="plugin types as written in YAML (my_robot_dc/Battery)")
    p.set_defaults(func=cmd_check_plugin)

    p = sub.add_parser("pub", help="publish a dc_interfaces/StringStamped record")
    p.add_argument("topic", help="a relative name (dc/measurement/x) is in --namespace")
    p.add_argument("json", help="the record, a JSON object; - reads records from stdin, a JSON object a line")
    add_namespace_argument(p)
    p.add_argument("--count", type=int, default=1, help="records to publish (0 = until Ctrl-C)")
    p.add_argument("--rate", type=float, default=1.0, help="records per second when count > 1")
    p.add_argument("--group-key", default="")
    p.add_argument(
        "--wait-matched", type=float, default=5.0, help="seconds to wait for a subscriber (none: exit 3, nothing sent)"
    )
    p.add_argument("--no-wait", action="store_true", help="publish at once, whether anyone subscribes or not")
    p.add_argument(
        "--linger", type=float, default=5.0, help="at most this many seconds to wait for subscribers' acknowledgements"
    )
    p.set_defaults(func=cmd_pub)

    p = sub.add_parser("status", help="counters of the running DC servers")
    add_metrics_target_arguments(p)
    p.add_argument("--json", action="store_true", help="print the raw JSON")
    p.add_argument("--wide", action="store_true", help="every counter, wider than 100 columns")
    p.set_defaults(func=cmd_status)

    add_top_arguments(sub.add_parser("top", help="records/s, pending and failures of the running servers, refreshed"))
    add_tap_arguments(
        sub.add_parser("tap", help="records as they pass on a measurement's, group's or destination's topics")
    )

    p = sub.add_parser("buffer", help="inspect the durable buffer: dead letters, replay, purge, salvage a damaged file")
    p.add_argument("action", choices=["list", "show", "replay", "purge", "stats", "salvage"])
    p.add_argument("ids", nargs="*", help="dead-letter ids (show, replay); the set-aside damaged file (salvage)")
    p.add_argument("--storage-path", default="", help="buffer folder (flb.storage_path)")
    p.add_argument("--into", default="", help="salvage: buffer folder to put the records in (else as --storage-path)")
    p.add_argument("--params", default="", help="read the storage path from this parameter file")
    p.add_argument(
        "--namespace",
        default="/",
        help="ROS namespace of the destination server, for the default buffer folder (with $ROS_DOMAIN_ID)",
    )
    p.add_argument("--destination", default="", help="only this destination")
    p.add_argument("--all", action="store_true", help="replay or purge every dead letter")
    p.add_argument("--json", action="store_true", help="list: one JSON object per dead letter, error in full")
    p.set_defaults(func=cmd_buffer)

    p = sub.add_parser("replay", help="play a rosbag2 bag (SQLite3 or MCAP) to its topics, with /clock")
    p.add_argument("bag", help="the bag's folder (with metadata.yaml)")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor of the recorded pace (default 1)")
    p.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics (default: all)")
    p.add_argument("--no-clock", action="store_true", help="do not publish the bag's time on /clock")
    p.add_argument(
        "--delay", type=float, default=1.0, help="seconds between creating the publishers and the first message"
    )
    p.add_argument(
        "--wait-for",
        nargs="+",
        metavar="TOPIC[=N]",
        help="before playing, wait until TOPIC has N subscribers (default 1), e.g. --wait-for /tf=2 /odom",
    )
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("lifecycle", help="start, pause, resume, reset or shut down the servers of a dc-bringup")
    p.add_argument("command_name", metavar="command", choices=LIFECYCLE_COMMANDS, help=", ".join(LIFECYCLE_COMMANDS))
    add_namespace_argument(p)
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for the manager and its answer")
    p.set_defaults(func=cmd_lifecycle)

    p = sub.add_parser("trigger", help="trigger a Recorder measurement: the raw data around now, as an MCAP file")
    p.add_argument("name", help="the Recorder measurement's name in the parameter file")
    p.add_argument("--reason", help="the reason kept in the incident's record (default: service)")
    add_namespace_argument(p)
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the recorder and its answer")
    p.set_defaults(func=cmd_trigger)

    p = sub.add_parser(
        "servers", help="run the local PostgreSQL, S3 (SeaweedFS) and InfluxDB for trying DC, until Ctrl-C"
    )
    p.add_argument("action", choices=["run"], help="run: start them, wait for Ctrl-C, stop them")
    p.add_argument(
        "names",
        nargs="*",
        metavar="server",
        help="postgres, s3, influxdb (default: these three); nats: a 3-node JetStream cluster (docs/fleet.md)",
    )
    p.add_argument("--state-dir", default="var/dc/servers", help="their data, logs and settings.yaml")
    p.set_defaults(func=cmd_servers)

    p = sub.add_parser("service", help="DC as a systemd service: the unit, its environment file for secrets")
    from dc_bringup.service import add_arguments as add_service_arguments
    from dc_bringup.service import main as service_main

    add_service_arguments(p)
    p.set_defaults(func=service_main)

    p = sub.add_parser("dashboard", help="what DC stored in PostgreSQL and S3, and its health, in a browser")
    from dc_dashboard.cli import add_arguments

    add_arguments(p)
    p.set_defaults(func=cmd_dashboard)

    p = sub.add_parser(
        "reconcile",
        help="objects without a row, rows without an object, files marked uploaded but missing: for a robot and "
        "a time range, between the bucket, the records table and files_metrics (--repair: see dc reconcile --help)",
    )
    from dc_bringup.reconcile import add_arguments as add_reconcile_arguments

    add_reconcile_arguments(p)
    p.set_defaults(func=cmd_reconcile)

    p = sub.add_parser(
        "demo", help="the QR-code demo into PostgreSQL and S3 with the dashboard, all started and stopped together"
    )
    p.add_argument("--port", type=int, default=8088, help="the dashboard's port on 127.0.0.1 (default 8088)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: at Ctrl-C)")
    p.add_argument("--rate", type=float, default=1.0, help="the simulated robot's speed-up (simulated s per s)")
    p.add_argument(
        "--state-dir", default="var/dc/demo", help="the children's logs and the servers' data (default var/dc/demo)"
    )
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "ingest",
        help="the fleet side: a NATS JetStream consumer into the destinations of a params file (docs/fleet.md)",
    )
    p.add_argument("params", help="parameter file whose destination_server section names the destinations")
    p.add_argument("--servers", action="append", default=[], help="NATS URL(s), comma-separated or repeated")
    p.add_argument("--stream", default="DC", help="JetStream stream (default DC)")
    p.add_argument("--consumer", default="ingest", help="durable pull consumer, shared by the workers (default ingest)")
    p.add_argument("--filter", default="dc.>", help="subjects to take (default dc.>)")
    p.add_argument("--batch", type=int, default=500, help="messages fetched at once (default 500)")
    p.add_argument(
        "--ack-wait", type=float, default=60.0, help="seconds before an unacknowledged message is redelivered"
    )
    p.add_argument("--max-in-flight", type=int, default=5000, help="messages taken and not yet acknowledged, at most")
    p.add_argument(
        "--handback-delay",
        type=float,
        default=5.0,
        help="seconds before a message whose record the worker's buffer dropped is delivered again (default 5)",
    )
    p.add_argument("--storage-path", required=True, help="folder of this worker's buffer (one per worker)")
    p.set_defaults(func=cmd_ingest)

    # Listed for `dc --help`; main() hands `dc sim ...` to the simulator's own parser.
    sub.add_parser("sim", help="a simulated robot: odometry, TF, /map, /cmd_vel (dc sim --help)", add_help=False)
    return parser


# The commands that start a ROS node: their output (records, JSON, answers scripts read) on standard output,
# Fast DDS's own lines on standard error (dc_core.native_stdout).
ROS_COMMANDS = frozenset({"pub", "tap", "top", "lifecycle", "trigger", "replay", "sim"})


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] and argv[0] in ROS_COMMANDS:
        from dc_core.native_stdout import python_only_stdout

        python_only_stdout()
    if argv[:1] == ["sim"]:
        # Every option after "sim" is the simulator's (argparse's REMAINDER drops leading options).
        from dc_sim.node import main as sim_main

        return sim_main(argv[1:])
    ros_args: list[str] = []
    if argv[:1] == ["validate"]:
        # As dc-bringup takes them (the servers' ROS arguments): not options of the command.
        from dc_core.ros_args import split_ros_args

        argv, ros_args = split_ros_args(argv)
    args = build_parser().parse_args(argv)
    args.ros_args = ros_args
    code: int = args.func(args)
    return code


if __name__ == "__main__":
    sys.exit(main())
