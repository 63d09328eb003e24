"""Lifecycle states that tell the truth, through `dc-bringup` and `dc lifecycle` (issue 31, item 4).

A transition that hangs, a server that cannot say its state, a teardown that stops part-way and a
deactivate that legitimately takes its destination's whole flb.grace: what a user relies on is that
`dc lifecycle pause` exits non-zero with one line naming the server when the servers are not where
it asked, that the manager restarts a server left in a state it cannot go on from, that a slow stop
is waited for (never sent twice) — and that every record still arrives (delivered + counted = sent).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from tests.bringup_util import BIN, FAST_DDS_LOG_LINE, Bringup, dc
from tests.fault_helpers import fault_env
from tests.http_receiver import Receiver, Request
from tests.test_e2e_delivery_failures import finish, publish, write_params

pytestmark = pytest.mark.e2e

BATCH = 40


def delivered(receiver: Receiver, padding: int) -> set[int]:
    """The distinct records of one publishing (told apart by their padding) the receiver accepted."""
    return {int(r["seq"]) for r in receiver.records() if len(r["pad"]) == padding}


def wait_delivered(receiver: Receiver, padding: int, count: int = BATCH, timeout: float = 30) -> None:
    receiver.wait_until(lambda: len(delivered(receiver, padding)) == count, timeout, f"{count} records of {padding}")


def lifecycle(run: Bringup, command: str, timeout: float = 30) -> tuple[int, list[str]]:
    result = dc("lifecycle", command, "--timeout", str(timeout), env=run.env, timeout=timeout + 30)
    return result.returncode, (result.stdout + result.stderr).strip().splitlines()


def pid_of(run: Bringup, server: str) -> int:
    match = re.search(r"\(pid (\d+)\)", run.wait_stderr(f"{server} active (pid"))
    assert match
    return int(match.group(1))


def wait_paused(run: Bringup) -> None:
    """Until every server is inactive again (a restarted one comes back paused)."""

    def paused() -> bool:
        code, out = lifecycle(run, "is-active", 10)
        return code == 1 and out[0].startswith("not active: servers inactive") and "not up" not in out[0]

    run.wait_until(paused, 40, "every server inactive")


def test_a_deactivate_that_hangs_fails_pause_with_the_server_named_and_it_is_restarted(tmp_path: Path) -> None:
    target = "dc_destinations.delivery:DeliveryPipeline.stop"  # (the server module runs as __main__)
    with (
        Receiver() as receiver,
        Bringup(
            write_params(tmp_path, receiver.port),
            tmp_path / "home",
            args=["--transition-timeout", "3", "--bond-timeout", "4"],
            env=fault_env(tmp_path, target, hang_s=120),
        ) as run,
    ):
        run.wait_ready()
        finish(publish(run, BATCH, rate=500, padding=1))
        wait_delivered(receiver, 1)

        code, out = lifecycle(run, "pause")
        assert code == 1 and len(out) == 1, out
        assert out[0].startswith("pause: failed: destination_server: deactivate did not finish in 3 s"), out
        # Sent once: a request to a server that hangs is not sent again (its retries would log "sending it
        # again", checked at the end); this said so by a duration, which a loaded machine stretched.
        assert "it hangs" in out[0], out
        assert (tmp_path / "fault-raised").exists()

        # Its heartbeat stopped with its loop: killed, started again, and brought back paused.
        run.wait_stderr("destination_server no heartbeat for", 20)
        wait_paused(run)
        assert lifecycle(run, "resume")[0] == 0
        finish(publish(run, BATCH, rate=500, padding=2))
        wait_delivered(receiver, 2)
    assert len(delivered(receiver, 1)) + len(delivered(receiver, 2)) == 2 * BATCH, "delivered = sent"
    assert not [line for line in run.stderr if "sending it again" in line]


def test_a_server_whose_state_cannot_be_read_fails_pause_with_its_name(tmp_path: Path) -> None:
    with (
        Receiver() as receiver,
        Bringup(write_params(tmp_path, receiver.port), tmp_path / "home", args=["--bond-timeout", "60"]) as run,
    ):
        run.wait_ready()
        finish(publish(run, BATCH, rate=500, padding=1))
        wait_delivered(receiver, 1)
        pid = pid_of(run, "destination_server")
        os.kill(pid, signal.SIGSTOP)  # a hung server: it answers nothing
        try:
            code, out = lifecycle(run, "pause")
        finally:
            os.kill(pid, signal.SIGCONT)
        assert code == 1 and len(out) == 1, out
        assert out[0] == (
            "pause: failed: destination_server: its state cannot be read (no answer to get_state in 5 s) "
            "(see dc-bringup log)"
        ), out
        # The others were paused all the same; once it answers again, a pause takes it there too.
        assert lifecycle(run, "pause") == (0, ["pause: done"])
        assert lifecycle(run, "resume") == (0, ["resume: done"])
        finish(publish(run, BATCH, rate=500, padding=2))
        wait_delivered(receiver, 2)
    assert len(delivered(receiver, 1)) + len(delivered(receiver, 2)) == 2 * BATCH, "delivered = sent"


def test_a_deactivate_that_stops_part_way_ends_in_error_and_the_server_is_restarted_without_loss(
    tmp_path: Path,
) -> None:
    # The pipeline's stop raises once: the subscriptions are gone, the buffer's senders still run.
    target = "dc_destinations.delivery:DeliveryPipeline.stop"
    with (
        Receiver() as receiver,
        Bringup(write_params(tmp_path, receiver.port), tmp_path / "home", env=fault_env(tmp_path, target)) as run,
    ):
        run.wait_ready()
        finish(publish(run, BATCH, rate=500, padding=1))
        wait_delivered(receiver, 1)
        receiver.status = 503  # the next records wait in the buffer across what follows
        finish(publish(run, BATCH, rate=500, padding=2))
        receiver.wait_until(lambda: len(receiver.requests) > 1, 10, "a refused attempt")

        code, out = lifecycle(run, "pause")
        assert code == 1 and len(out) == 1, out
        assert out[0].startswith(
            "pause: failed: destination_server: deactivate failed part-way and left it unconfigured"
        ), out
        # The server said what happened and where it is: not "active" with nothing listening.
        run.wait_stderr("deactivate stopped part-way: the transition ends in ERROR")
        run.wait_stderr("destination_server is unconfigured after an error")
        run.wait_stderr(
            "destination_server is unconfigured after a failed transition (its log above says why): restarting"
        )
        wait_paused(run)
        receiver.status = 200
        assert lifecycle(run, "resume")[0] == 0
        wait_delivered(receiver, 2)
        finish(publish(run, BATCH, rate=500, padding=3))
        wait_delivered(receiver, 3)
    assert sum(len(delivered(receiver, padding)) for padding in (1, 2, 3)) == 3 * BATCH, "delivered = sent"
    assert not [line for line in run.stderr if "could not be committed" in line]


def test_a_resume_whose_activate_fails_says_so_and_the_server_is_restarted_active(tmp_path: Path) -> None:
    # measurement_server's second activate (the resume) fails once; its first, at start-up, does not.
    target = "dc_core.lifecycle:ManagedServer.start_metrics_http"
    with (
        Receiver() as receiver,
        Bringup(
            write_params(tmp_path, receiver.port),
            tmp_path / "home",
            args=["--bond-timeout", "3"],
            env=fault_env(tmp_path, target, skip=1),
        ) as run,
    ):
        run.wait_ready()
        assert lifecycle(run, "pause") == (0, ["pause: done"])
        code, out = lifecycle(run, "resume")
        assert code == 1 and len(out) == 1, out
        assert out[0] == (
            "resume: failed: measurement_server: activate failed; it is still inactive (its log above says why) "
            "(see dc-bringup log)"
        ), out
        # Not "active" while it is not: is_active names it until the watch has restarted it active.
        code, out = lifecycle(run, "is-active", 10)
        assert code == 1 and "not up: measurement_server" in out[0], out
        run.wait_stderr("measurement_server did not come up: restarting it", 20)
        run.wait_until(lambda: lifecycle(run, "is-active", 10)[0] == 0, 30, "every server active")
        finish(publish(run, BATCH, rate=500, padding=1))
        wait_delivered(receiver, 1)
    assert len(delivered(receiver, 1)) == BATCH, "delivered = sent"


def test_a_deactivate_as_long_as_a_15_s_grace_is_sent_once_and_succeeds(tmp_path: Path) -> None:
    stall = threading.Event()
    stalled = threading.Event()
    answer_now = threading.Event()

    def answer(request: Request) -> tuple[int, bytes]:
        if stall.is_set():
            # An endpoint that takes its time: a send still running when the grace ends.
            stalled.set()
            answer_now.wait(60)
            return 503, b"later"
        return 200, b"ok"

    with Receiver(answer) as receiver:
        params = write_params(tmp_path, receiver.port)
        text = params.read_text().replace("      http_port: 0\n", "      http_port: 0\n      grace: 15.0\n")
        params.write_text(text.replace("timeout: 2.0", "timeout: 60.0"))
        with Bringup(params, tmp_path / "home") as run:
            run.wait_ready()
            stall.set()
            finish(publish(run, BATCH, rate=500, padding=1))
            assert stalled.wait(10)

            # The send in flight ends 18 s into the pause: the pipeline waits the 15 s grace for it,
            # then the deactivate returns and the plugin's own teardown waits for the send's end
            # (dc_destinations.sender.Gate) — a transition longer than the old fixed 10 s timeout.
            pause = subprocess.Popen(
                [str(BIN / "dc"), "lifecycle", "pause", "--timeout", "60"],
                env=run.env,
                stdout=subprocess.PIPE,
                text=True,
            )
            answer_at = threading.Timer(18.0, answer_now.set)
            try:
                run.wait_stderr("manage_nodes: bringing every server to inactive")
                started = time.monotonic()
                answer_at.start()
                out, _ = pause.communicate(timeout=90)
            finally:
                answer_at.cancel()
                answer_now.set()
            assert (pause.returncode, FAST_DDS_LOG_LINE.sub("", out).strip()) == (0, "pause: done")
            took = time.monotonic() - started
            assert took >= 15, took
            run.wait_stderr("still running after the 15 s grace")
            assert not [line for line in run.stderr if "sending it again" in line or "asking again" in line]
            # A slow transition is no missing heartbeat: nothing was restarted.
            assert not [line for line in run.stderr if "restarting it" in line], "\n".join(run.stderr)

            stall.clear()
            assert lifecycle(run, "resume") == (0, ["resume: done"])
            wait_delivered(receiver, 1)
    assert len(delivered(receiver, 1)) == BATCH, "delivered = sent"
