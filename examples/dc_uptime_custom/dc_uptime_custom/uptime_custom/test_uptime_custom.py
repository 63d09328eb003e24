"""UptimeCustom as its server would drive it, without a server: dc_core.testing's harness."""

from __future__ import annotations

import jsonschema

from dc_core.testing import FakeContext, PluginHarness
from dc_measurements.uptime import Uptime

from . import UptimeCustom


def test_it_collects_what_uptime_collects_and_its_own_schema_rejects_it() -> None:
    harness = PluginHarness()
    plugin = harness.start(UptimeCustom, {})
    sample = plugin.collect()
    harness.stop(plugin)
    assert sample is not None and sample["time"] > 0
    own, builtin = UptimeCustom.load_schema(), Uptime.load_schema()
    assert own is not None and builtin is not None and own != builtin, "the subclass brings its own schema"
    assert jsonschema.Draft7Validator(builtin).is_valid(sample)
    assert not jsonschema.Draft7Validator(own).is_valid(sample)


def test_the_failed_validation_hook_logs_and_counts_each_failure() -> None:
    harness = PluginHarness()
    plugin = harness.start(UptimeCustom, {})
    assert plugin.counters() == {"failed_validations": 0}
    for seconds in (120, 125):
        plugin.on_failed_validation({"time": seconds}, f"time: {seconds} is greater than the maximum of 0")
    harness.stop(plugin)
    assert plugin.counters() == {"failed_validations": 2}
    assert isinstance(plugin.context, FakeContext)
    assert plugin.context.logger.at("info")[-1] == "on_failed_validation called for time=125 (2 so far)"
