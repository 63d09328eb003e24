"""One measurement at run time: gating, validation, record building, publication.

Kept free of ROS so it can be tested directly; the server wires ``publish`` to a lifecycle
publisher and calls :meth:`MeasurementRunner.tick` from the measurement's timer.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from dc_core.gating import Gate
from dc_core.jsonpath import flatten as flatten_record
from dc_core.logs import BurstLog, Logger
from dc_core.measurement import Measurement
from dc_core.records import MalformedRecord, dump_parsed, dump_record
from dc_core.worker import Outcome, Worker
from dc_measurements.condition_runtime import ConditionRuntime, already_unmet, conditions_met
from dc_measurements.config import MeasurementConfig
from dc_measurements.metadata import apply_metadata
from dc_measurements.validation import RecordValidator

PublishFn = Callable[[str, str, int | None], None]
"""publish(json_text, group_key, stamp_ns or None for now)."""


@dataclass
class RunnerStats:
    collected: int = 0
    published: int = 0
    empty: int = 0
    invalid: int = 0
    gated: int = 0
    errors: int = 0
    overrun: int = 0


@dataclass(frozen=True)
class _Plan:
    """A period that collects: ``met`` is the verdict of conditions judged without the sample, if any;
    ``known`` the states of those judged already (not judged again with the sample)."""

    met: bool | None
    known: dict[str, bool] = field(default_factory=dict)
    # Since when the conditions judged without the sample have allowed collecting (node clock).
    allowed_since_ns: int | None = None


class MeasurementRunner:
    def __init__(
        self,
        config: MeasurementConfig,
        plugin: Measurement[Any],
        conditions: dict[str, ConditionRuntime],
        validator: RecordValidator | None,
        run_id: str | None,
        custom: list[tuple[str, str, bool]],
        publish: PublishFn,
        logger: Logger,
        clock_ns: Callable[[], int] = time.time_ns,
        schema_version: int | None = None,
    ) -> None:
        self.config = config
        self._schema_version = schema_version
        self.plugin = plugin
        self.validator = validator
        self._conditions = conditions
        self._run_id = run_id
        self._custom = custom
        self._publish = publish
        self._dump = dump_parsed if plugin.samples_are_parsed_json else dump_record
        self._logger = logger
        # The node's clock (simulated time under use_sim_time): stamps of samples collected on the worker.
        self._clock_ns = clock_ns
        common = config.common
        gated = bool(config.conditions) and not plugin.conditions_trigger
        if plugin.conditions_trigger:
            plugin.has_trigger_conditions = bool(config.conditions)
        self.gate = Gate(common.init_max_measurements, common.condition_max_measurements, gated)
        self.stats = RunnerStats()
        self._empty_warned = False
        self._collecting = False
        # Bumped at each activation and deactivation: a collection that finishes in another one
        # than it started in is not published.
        self._generation = 0
        self._allowed_since_ns: int | None = None
        self._predates_log = BurstLog(
            logger.info,
            f"measurement {config.name}: samples dated before their conditions held were not published",
        )
        self._overrun_log = BurstLog(
            logger.warning,
            f"measurement {config.name}: polls skipped, the previous collection was still running",
        )

    def set_active(self, active: bool) -> None:
        """Called by the server at activation and deactivation (see ``tick_in_worker``)."""
        self._generation += 1
        self._collecting = False

    @property
    def finished(self) -> bool:
        return self.gate.finished

    def _used_conditions(self) -> list[ConditionRuntime]:
        return [self._conditions[c] for c in dict.fromkeys(self.config.conditions)]

    def _evaluate(self, sample: dict[str, Any] | None, known: dict[str, bool] | None = None) -> bool:
        # Each condition is evaluated exactly once per sample, even when listed twice.
        known = known or {}
        states = {
            rt.name: known[rt.name] if rt.name in known else rt.evaluate(sample) for rt in self._used_conditions()
        }
        c = self.config.common
        return conditions_met(c.if_all_conditions, c.if_any_conditions, c.if_none_conditions, states)

    def tick(self) -> None:
        """One polling period of a timer-driven measurement, collected on this thread."""
        if self.plugin.conditions_trigger:
            self._poll_trigger()
            return
        plan = self._plan()
        if plan is not None:
            self._collected(plan, self._collect_outcome(self.plugin.collect_stamped))

    def tick_in_worker(self, worker: Worker) -> None:
        """One polling period whose collection runs on ``worker`` (``collect_in_worker`` plugins).

        The conditions that do not need the sample are judged now, the sample's own when it comes
        back. A period that comes while the previous collection still runs is skipped and counted
        as ``overrun``: collections of one measurement never overlap.
        """
        if self.plugin.conditions_trigger:
            self._poll_trigger()
            return
        self._overrun_log.tick()
        if self._collecting:
            self.stats.overrun += 1
            self._overrun_log.event(1, f"polling_interval {self.config.common.polling_interval} ms")
            return
        plan = self._plan()
        if plan is None:
            return
        self._collecting = True

        def collect() -> tuple[dict[str, Any] | None, int | None, str | None]:
            sample, stamp_ns, group_key = self.plugin.collect_stamped()
            # Stamped when collected, not when the main thread gets to it.
            return sample, stamp_ns if stamp_ns is not None else self._clock_ns(), group_key

        generation = self._generation

        def on_done(outcome: Outcome[tuple[dict[str, Any] | None, int | None, str | None]]) -> None:
            if generation != self._generation:
                return
            self._collecting = False
            self._collected(plan, self._collect_outcome(outcome.get))

        worker.submit(collect, on_done)

    def _poll_trigger(self) -> None:
        met = self._evaluate(None) if self.config.conditions else None
        try:
            self.plugin.on_poll(met)
        except Exception as exc:  # one failing poll must not stop the measurement
            self.stats.errors += 1
            self._logger.error(f"measurement {self.config.name}: poll failed: {exc!r}")

    def _plan(self) -> _Plan | None:
        """Whether this period collects, and the verdict of conditions judged without the sample."""
        if self.gate.finished:
            return None
        if not self.gate.needs_conditions:
            return _Plan(None)
        self._predates_log.tick()
        used = self._used_conditions()
        if not any(rt.needs_sample for rt in used):
            met = self._evaluate(None)
            self._note_allowed(met)
            if not self.gate.would_admit(met):
                # Conditions are judged without the sample: do not even collect (#213 upstream).
                self.gate.observe_conditions(met)
                self.stats.gated += 1
                return None
            return _Plan(met, allowed_since_ns=self._allowed_since_ns)
        # Some need the sample; when those that do not already rule it out (the robot moves, for a camera
        # gated by if_none_conditions: [moving]) the frame is not even read.
        c = self.config.common
        known = {rt.name: rt.evaluate(None) for rt in used if not rt.needs_sample}
        unmet = already_unmet(c.if_all_conditions, c.if_none_conditions, known)
        self._note_allowed(not unmet)
        if unmet:
            self.gate.observe_conditions(False)
            self.stats.gated += 1
            return None
        return _Plan(None, known, self._allowed_since_ns)

    def _note_allowed(self, allowed: bool) -> None:
        if not allowed:
            self._allowed_since_ns = None
        elif self._allowed_since_ns is None:
            self._allowed_since_ns = self._clock_ns()

    def _collected(self, plan: _Plan, collected: tuple[dict[str, Any] | None, int | None, str | None]) -> None:
        sample, stamp_ns, group_key = collected
        if sample is None:
            return
        if plan.allowed_since_ns is not None and stamp_ns is not None and stamp_ns < plan.allowed_since_ns:
            # A sample dated by its source (a camera frame) may predate the moment the conditions
            # were seen to hold: the picture taken while the robot still moved is not the one
            # "taken while standing". Skipped without counting against condition_max_measurements:
            # the next period brings a newer one.
            self.stats.gated += 1
            self._predates_log.event(1, f"{(plan.allowed_since_ns - stamp_ns) / 1e9:.3f} s before")
            return
        if plan.met is not None:
            met = plan.met
        else:
            met = self._evaluate(sample, plan.known) if self.gate.needs_conditions else True
        self._offer(sample, met, stamp_ns, group_key)

    def emit(self, sample: dict[str, Any], stamp_ns: int | None = None, group_key: str | None = None) -> None:
        """A record from an event-driven measurement."""
        if self.gate.finished:
            return
        if not self._check_sample(sample):
            return
        self.stats.collected += 1
        met = self._evaluate(sample) if self.gate.needs_conditions else True
        self._offer(sample, met, stamp_ns, group_key)

    def _collect_outcome(
        self, collect: Callable[[], tuple[dict[str, Any] | None, int | None, str | None]]
    ) -> tuple[dict[str, Any] | None, int | None, str | None]:
        try:
            sample, stamp_ns, group_key = collect()
        except Exception as exc:  # one failing collect must not stop the measurement
            self.stats.errors += 1
            self._logger.error(f"measurement {self.config.name}: collect failed: {exc!r}")
            return None, None, None
        if not self._check_sample(sample):
            return None, None, None
        self.stats.collected += 1
        return sample, stamp_ns, group_key

    def _check_sample(self, sample: Any) -> bool:
        if sample is None or sample == {}:
            self.stats.empty += 1
            if not self._empty_warned:
                # Said once: subscribe-and-clear plugins are empty on every tick without input.
                self._logger.info(f"measurement {self.config.name}: nothing to report (said once)")
                self._empty_warned = True
            return False
        if not isinstance(sample, dict):
            self.stats.errors += 1
            self._logger.error(
                f"measurement {self.config.name}: collect returned {type(sample).__name__}, expected a JSON object"
            )
            return False
        self._empty_warned = False
        return True

    def _offer(self, sample: dict[str, Any], met: bool, stamp_ns: int | None, group_key: str | None) -> None:
        if not self.gate.admit(met):
            self.stats.gated += 1
            return
        record = self.build_record(sample)
        if record is None:
            return
        try:
            text = self._dump(record)
        except MalformedRecord as exc:  # a plugin's sample with NaN, a lone surrogate (a file name), ...
            self.stats.errors += 1
            self._logger.error(f"measurement {self.config.name}: record not published: {exc}")
            return
        self._publish(text, self.config.common.group_key if group_key is None else group_key, stamp_ns)
        if self.config.common.debug:
            self._logger.info(f"measurement {self.config.name} published: {text}")
        self.stats.published += 1
        try:
            self.plugin.on_published(sample)
        except Exception as exc:  # a plugin's bug must not stop the measurement
            self.stats.errors += 1
            self._logger.error(f"measurement {self.config.name}: on_published raised {exc!r}")

    def build_record(self, sample: dict[str, Any]) -> dict[str, Any] | None:
        """Validate, nest, flatten and add metadata; None when the record is dropped."""
        c = self.config.common
        if self.validator is not None:
            error = self.validator.error(sample)
            if error is not None:
                self.stats.invalid += 1
                action = "dropped" if c.drop_invalid else "published anyway"
                self._logger.error(f"measurement {self.config.name}: validation failed ({action}): {error}")
                try:
                    self.plugin.on_failed_validation(sample, error)
                except Exception as exc:
                    self._logger.error(f"measurement {self.config.name}: on_failed_validation raised {exc!r}")
                if c.drop_invalid:
                    return None
        record: dict[str, Any] = dict(sample)
        if c.nested:
            record = {self.config.name: record}
        if c.flatten:
            record = flatten_record(record)
        if c.nested:
            record["nested"] = True
        if c.flatten:
            record["flattened"] = True
        return apply_metadata(
            record,
            run_id=self._run_id,
            schema_version=self._schema_version,
            tags=c.tags,
            name=self.config.name if c.include_measurement_name else None,
            plugin=c.plugin if c.include_measurement_plugin else None,
            custom=self._custom,
        )
