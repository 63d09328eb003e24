"""``dc check``: a preflight of a parameter file against the real world, before running it.

``dc validate`` reads the file only. ``dc check`` then does what the servers would do first, once:
each destination's read-only probe with its real credentials (``Destination.probe``), a test
record through ``send`` only with ``--write-test``, each timer-driven measurement's ``collect``
(its sample checked against its schema), and each of its conditions judged on that sample. The
plugins are made, configured and activated as the servers make them, through
:mod:`dc_core.testing`'s contexts, without ROS: a measurement or condition that needs a ROS node
(it listens to topics) is said to be skipped, not failed.

What is printed comes from the plugins' own messages, which mask their secrets; every value of a
parameter declared ``secret`` is masked again here, should one slip through.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shutil
import sys
import textwrap
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from dc_core.destination import ConfigurationProblem, OutgoingRecord, ProbeResult, RetryableError
from dc_core.errors import DcError
from dc_core.testing import FakeContext, RecordingLogger

OK, FAILED, SKIPPED, WARN = "ok", "failed", "skipped", "warn"
WIDTH = 100
_COMPONENT = 30
_RESULT = 8


@dataclass(frozen=True)
class Row:
    component: str
    result: str  # OK, FAILED, SKIPPED or WARN (only FAILED makes dc check fail)
    reason: str
    fix: str = ""


def _logger() -> RecordingLogger:
    # The plugins' log lines are kept for the reasons, not printed between the table's rows.
    log = logging.getLogger("dc.check")
    log.propagate = False
    if not log.handlers:
        log.addHandler(logging.NullHandler())
    return RecordingLogger("dc.check")


def _failure(exc: BaseException) -> tuple[str, str]:
    """(reason, fix) of an exception a plugin raised."""
    fix = exc.fix if isinstance(exc, ConfigurationProblem) else ""
    text = str(exc) or type(exc).__name__
    if not isinstance(exc, (DcError, RetryableError)):
        text = f"{type(exc).__name__}: {text}"
    return text, fix


def _configured(component: str, config: Any, context: FakeContext) -> Any:
    """The plugin of ``config`` (a destination's or condition's), made and configured as its server
    does; a failed Row when that fails."""
    try:
        plugin = config.plugin_class(context, config.plugin_params)
        plugin.on_configure()
    except Exception as exc:
        context.stop_worker()
        reason, fix = _failure(exc)
        return Row(component, FAILED, f"cannot configure: {reason}", fix)
    return plugin


# -- destinations ------------------------------------------------------------------------------------
def check_destination(dest: Any, write_test: bool) -> list[Row]:
    component = f"destination {dest.name}"
    context = FakeContext(name=dest.name, logger=_logger())
    plugin = _configured(component, dest, context)
    if isinstance(plugin, Row):
        return [plugin]
    rows: list[Row] = []
    try:
        try:
            result: ProbeResult | None = plugin.probe()
        except Exception as exc:
            reason, fix = _failure(exc)
            result = ProbeResult(False, reason, fix)
        if result is None:
            rows.append(Row(component, SKIPPED, f"{dest.common.plugin} has no probe (nothing checked)"))
        else:
            # A probe that says nothing more failed to reach its server: what to check then is always the same.
            fix = result.fix or "check that the server runs and the host, port or endpoint"
            rows.append(Row(component, OK if result.ok else FAILED, result.reason, "" if result.ok else fix))
        if write_test and (result is None or result.ok):
            rows.append(_write_test(dest, plugin))
    finally:
        try:
            plugin.on_cleanup()
        finally:
            context.stop_worker()
    return rows


def _write_test(dest: Any, plugin: Any) -> Row:
    from dc_core.confined_files import ConfinementParams

    component = f"destination {dest.name} write"
    if isinstance(dest.plugin_params, ConfinementParams):
        return Row(component, SKIPPED, "it uploads the files records name: a test record names none")
    stamp_ns = time.time_ns()
    record_id = f"dc-check-{uuid.uuid4()}"
    data = {"dc_check": "write test of dc check", "time": stamp_ns / 1e9, "record_id": record_id}
    record = OutgoingRecord(record_id, "/dc/check", stamp_ns, data)
    try:
        plugin.on_activate()
        try:
            outcome = plugin.send([record])
        finally:
            plugin.on_deactivate()
    except Exception as exc:
        if "needs a ROS node" in str(exc):  # Rcl publishes on ROS topics: dc check runs without ROS
            return Row(component, SKIPPED, "it needs ROS: run dc-bringup to see its records")
        reason, fix = _failure(exc)
        return Row(component, FAILED, f"test record not written: {reason}", fix)
    if outcome is not None and (outcome.retry or outcome.reject):
        why = next(iter({**outcome.retry, **outcome.reject}.values()))
        return Row(component, FAILED, f"test record not written: {why}")
    return Row(component, OK, f"test record {record_id} written")


# -- measurements and conditions -----------------------------------------------------------------------
def check_measurement(m: Any, conditions: dict[str, Any]) -> list[Row]:
    component = f"measurement {m.name}"
    context = FakeContext(name=m.name, logger=_logger())
    try:
        plugin = m.plugin_class(context, m.plugin_params)
        if not plugin.timer_driven:
            return [Row(component, SKIPPED, "publishes on ROS events: run dc-bringup to see its records")]
        plugin.on_configure()
    except Exception as exc:
        context.stop_worker()
        return [_measurement_failure(component, exc)]
    try:
        try:
            plugin.on_activate()
            sample, _, _ = plugin.collect_stamped()
        except Exception as exc:
            return [_measurement_failure(component, exc)]
        rows = [_sample_row(m, plugin, sample)]
        rows += [_judge(cid, conditions[cid], m.name, sample) for cid in dict.fromkeys(m.conditions)]
        return rows
    finally:
        _stop(plugin, context)


def _stop(plugin: Any, context: FakeContext) -> None:
    """Deactivated and cleaned up as a server does at shutdown, its worker threads stopped."""
    try:
        plugin.on_deactivate()
        plugin.on_cleanup()
    finally:
        context.stop_worker()


def _measurement_failure(component: str, exc: BaseException) -> Row:
    # FakeContext without a node raises "... needs a ROS node"; plugins that check for one say so too.
    if "needs a ROS node" in str(exc):
        return Row(component, SKIPPED, "needs ROS (topics, TF or timers): run dc-bringup to see its records")
    reason, fix = _failure(exc)
    return Row(component, FAILED, reason, fix)


def _sample_row(m: Any, plugin: Any, sample: Any) -> Row:
    component = f"measurement {m.name}"
    if sample is None:
        return Row(component, OK, "collected nothing this time (None): nothing to report yet")
    from dc_measurements.validation import RecordValidator

    error = None
    if m.common.enable_validator:
        try:
            validator = (
                RecordValidator.from_file(m.common.json_schema_path) if m.common.json_schema_path else None
            ) or (RecordValidator(schema, m.name) if (schema := plugin.load_schema()) is not None else None)
        except DcError as exc:
            return Row(component, FAILED, str(exc), "correct json_schema_path or the schema")
        error = validator.error(sample) if validator is not None else None
    if error is not None and m.common.drop_invalid:
        return Row(component, FAILED, f"sample fails its schema, dropped: {error}", "correct the plugin or schema")
    if error is not None:  # published all the same, as the server would: said, not failed
        return Row(component, WARN, f"sample fails its schema (published anyway, drop_invalid false): {error}")
    keys = ", ".join(map(str, sample)) if isinstance(sample, dict) else type(sample).__name__
    return Row(component, OK, f"collected a sample: {keys}")


def _judge(cid: str, condition: Any, measurement: str, sample: Any) -> Row:
    component = f"condition {cid} ({measurement})"
    if condition.common.topic:
        return Row(component, SKIPPED, f"judges the records of {condition.common.topic}: needs ROS")
    context = FakeContext(name=cid, logger=_logger())
    plugin = _configured(component, condition, context)
    if isinstance(plugin, Row):
        return plugin
    try:
        plugin.on_activate()
        try:
            active = bool(plugin.evaluate(sample if plugin.needs_sample else None))
        except Exception as exc:  # the server counts it inactive too; said, for it may never change
            return Row(component, OK, f"inactive on this sample: {type(exc).__name__}: {exc}")
        return Row(component, OK, "active on this sample" if active else "inactive on this sample")
    except Exception as exc:
        reason, fix = _failure(exc)
        return Row(component, FAILED, reason, fix)
    finally:
        _stop(plugin, context)


# -- the whole file --------------------------------------------------------------------------------------
def run_checks(configs: dict[str, Any], write_test: bool = False) -> list[Row]:
    rows: list[Row] = []
    destinations = configs.get("destination_server")
    if destinations is not None:
        for dest in destinations.destinations:
            rows += check_destination(dest, write_test)
    measurements = configs.get("measurement_server")
    if measurements is not None:
        for m in measurements.measurements:
            rows += check_measurement(m, measurements.conditions)
    return rows


def secrets_of(configs: dict[str, Any]) -> set[str]:
    """Every non-empty value of a parameter declared secret, in every plugin of the file."""
    found: set[str] = set()
    for config in configs.values():
        for plugin in [*getattr(config, "destinations", []), *getattr(config, "measurements", [])]:
            found |= _secret_values(plugin.plugin_params)
        for condition in getattr(config, "conditions", {}).values():
            found |= _secret_values(condition.plugin_params)
    return found


def _secret_values(params: Any) -> set[str]:
    if not dataclasses.is_dataclass(params):
        return set()
    values = set()
    for f in dataclasses.fields(params):
        value = getattr(params, f.name, None)
        if f.metadata.get("secret") and isinstance(value, str) and value:
            values.add(value)
        elif dataclasses.is_dataclass(value):
            values |= _secret_values(value)
    return values


def format_table(rows: Iterable[Row], secrets: Iterable[str] = (), width: int = WIDTH) -> str:
    """COMPONENT, RESULT, then the reason and its fix wrapped into the columns left: ``width`` wide."""
    masks = sorted((s for s in secrets if s), key=len, reverse=True)

    def mask(text: str) -> str:
        for secret in masks:
            text = text.replace(secret, "***")
        return text

    text_width = width - _COMPONENT - _RESULT
    lines = [f"{'COMPONENT':<{_COMPONENT}}{'RESULT':<{_RESULT}}REASON / FIX", "-" * width]
    for row in rows:
        detail = textwrap.wrap(mask(row.reason), text_width, break_on_hyphens=False) or [""]
        if row.fix:
            detail += textwrap.wrap("fix: " + mask(row.fix), text_width, break_on_hyphens=False)
        component = textwrap.wrap(row.component, _COMPONENT - 1) or [""]
        for i in range(max(len(detail), len(component))):
            left = component[i] if i < len(component) else ""
            result = row.result if i == 0 else ""
            right = detail[i] if i < len(detail) else ""
            lines.append(f"{left:<{_COMPONENT}}{result:<{_RESULT}}{right}".rstrip())
    return "\n".join(lines)


def main(params_file: str, namespace: str = "", write_test: bool = False) -> int:
    """Print the table; 0 when nothing failed, 1 when something did, 2 for an invalid file."""
    from dc_bringup.validate import check

    report, error = check(params_file, namespace)
    if report is None:
        print(f"invalid: {error}", file=sys.stderr)
        return 2
    rows = [Row("configuration", OK, f"valid: {', '.join(report.servers)}")]
    rows += [Row("configuration", WARN, w) for w in report.warnings]
    rows += run_checks(report.configs, write_test)
    width = min(WIDTH, max(60, shutil.get_terminal_size((WIDTH, 24)).columns))
    print(format_table(rows, secrets_of(report.configs), width))
    failed = [r for r in rows if r.result == FAILED]
    counts = {result: sum(r.result == result for r in rows) for result in (FAILED, OK, SKIPPED, WARN)}
    print("\n" + ", ".join(f"{n} {result}" for result, n in counts.items()))
    return 1 if failed else 0


def cmd_check(args: argparse.Namespace) -> int:
    return main(args.params_file, args.namespace, args.write_test)
