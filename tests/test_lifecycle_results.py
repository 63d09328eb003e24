"""dc_core.lifecycle: a transition's result and the node's state say what happened (issue 31, item 4).

A teardown that stops part-way ends in ERROR and on_error releases the rest (unconfigured, or
finalized when even that fails); one that went to its end but for a plugin's own hook succeeds
with an ERROR log; a failed configure or activate that is undone is a FAILURE back where it was.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.lifecycle import TransitionCallbackReturn

from dc_bringup.manager import default_transition_timeout
from dc_bringup.validate import validate_params_file
from dc_core.lifecycle import ManagedServer, PartialTeardown

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
ERROR = TransitionCallbackReturn.ERROR


class Faulty(ManagedServer):
    """A server whose steps raise what the test sets, and that records which steps ran."""

    def __init__(self, context: Context) -> None:
        super().__init__(f"dc_faulty_{uuid.uuid4().hex[:8]}", "", context=context)
        self.faults: dict[str, list[Exception]] = {}
        self.ran: list[str] = []
        self.logged: list[str] = []
        logger = self.get_logger()
        for level in ("error", "fatal"):
            original = getattr(logger, level)

            def log(message: str, original: Any = original, **kwargs: Any) -> Any:
                self.logged.append(message)
                return original(message, **kwargs)

            setattr(logger, level, log)

    def _step(self, name: str) -> None:
        self.ran.append(name)
        pending = self.faults.get(name)
        if pending:
            raise pending.pop(0)

    def configure_server(self) -> None:
        self._step("configure")

    def activate_server(self) -> None:
        self._step("activate")

    def deactivate_server(self) -> None:
        self._step("deactivate")

    def cleanup_server(self) -> None:
        self._step("cleanup")


@pytest.fixture
def server() -> Iterator[Faulty]:
    context = Context()
    rclpy.init(context=context)
    node = Faulty(context)
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)


def active(server: Faulty) -> Faulty:
    assert server.trigger_configure() == SUCCESS
    assert server.trigger_activate() == SUCCESS
    server.ran.clear()
    return server


def test_a_deactivate_that_stops_part_way_ends_in_error_and_on_error_leaves_it_unconfigured(server: Faulty) -> None:
    active(server).faults["deactivate"] = [RuntimeError("the pipeline's stop broke")]
    assert server.trigger_deactivate() == ERROR
    assert server.ran == ["deactivate", "cleanup"]  # on_error released what was left
    assert server.lifecycle_state == "unconfigured"  # not "active" with nothing running
    assert any("deactivate stopped part-way" in line for line in server.logged)
    # From there it can be configured and activated again.
    assert server.trigger_configure() == SUCCESS and server.trigger_activate() == SUCCESS


def test_when_on_errors_cleanup_fails_too_the_node_is_finalized(server: Faulty) -> None:
    active(server).faults.update(deactivate=[RuntimeError("broke")], cleanup=[RuntimeError("broke again")])
    assert server.trigger_deactivate() == ERROR
    assert server.lifecycle_state == "finalized"
    assert any("is finalized: it cannot go on" in line for line in server.logged)


def test_a_teardown_that_went_to_its_end_but_for_a_plugins_hook_succeeds_with_an_error_log(server: Faulty) -> None:
    active(server).faults["deactivate"] = [PartialTeardown("measurement m (x): on_deactivate failed: boom")]
    assert server.trigger_deactivate() == SUCCESS
    assert server.lifecycle_state == "inactive"
    assert "deactivate: done, but measurement m (x): on_deactivate failed: boom" in server.logged


def test_a_cleanup_that_stops_part_way_ends_in_error_and_is_tried_once_more(server: Faulty) -> None:
    active(server)
    assert server.trigger_deactivate() == SUCCESS
    server.faults["cleanup"] = [RuntimeError("a file would not close")]
    assert server.trigger_cleanup() == ERROR
    assert server.ran == ["deactivate", "cleanup", "cleanup"]
    assert server.lifecycle_state == "unconfigured"


def test_a_failed_activate_undone_is_a_failure_back_in_inactive(server: Faulty) -> None:
    assert server.trigger_configure() == SUCCESS
    server.faults["activate"] = [RuntimeError("no connection")]
    assert server.trigger_activate() == FAILURE
    assert server.lifecycle_state == "inactive"


def test_a_failed_activate_whose_undo_stops_part_way_ends_in_error(server: Faulty) -> None:
    assert server.trigger_configure() == SUCCESS
    server.faults.update(activate=[RuntimeError("no connection")], deactivate=[RuntimeError("and stuck")])
    assert server.trigger_activate() == ERROR
    assert server.lifecycle_state == "unconfigured"


def test_a_failed_configure_undone_is_a_failure_back_in_unconfigured(server: Faulty) -> None:
    server.faults["configure"] = [RuntimeError("bad file")]
    assert server.trigger_configure() == FAILURE
    assert server.lifecycle_state == "unconfigured"
    assert server.ran == ["configure", "cleanup"]


def test_the_default_transition_timeout_exceeds_the_destinations_grace(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    section = """
destination_server:
  ros__parameters:
    flb:
      grace: {grace}
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["dc/measurement/uptime"]
"""
    for grace, expected in ((15.0, 45.0), (1.0, 31.0)):
        params.write_text(section.format(grace=grace))
        assert default_transition_timeout(validate_params_file(params).configs) == expected
    assert default_transition_timeout({}) == 30.0  # no destination_server: nothing waits for a grace
