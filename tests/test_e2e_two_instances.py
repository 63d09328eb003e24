"""Two DC instances on one machine: each delivers its own records, or the second refuses to start.

The reported case: two dc-bringup runs (different ROS domains, different output folders, a File
destination named `out` in both, the default buffer location) shared one buffer, and each
delivered some of the other's records, silently. Both instances here share $HOME, as two runs
of one user do.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest

from tests.bringup_util import Bringup, dc

pytestmark = pytest.mark.e2e

RECORDS = 50


def write_params(folder: Path, storage_path: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    flb = f'    flb:\n      storage_path: "{storage_path}"\n' if storage_path else ""
    params = folder / "params.yaml"
    params.write_text(
        f"""destination_server:
  ros__parameters:
{flb}    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/File"
      inputs: ["/direct"]
      path: "{folder / "out"}"
      file: "records.jsonl"
"""
    )
    return params


def lines(folder: Path) -> list[dict[str, str]]:
    path = folder / "out" / "records.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_two_instances_with_the_default_buffer_each_deliver_exactly_their_own_records(tmp_path: Path) -> None:
    home = tmp_path / "home"
    with (
        Bringup(write_params(tmp_path / "a"), home) as a,
        Bringup(write_params(tmp_path / "b"), home) as b,
    ):
        for run, name in ((a, "a"), (b, "b")):
            run.wait_ready()
            published = dc(
                "pub", "/direct", json.dumps({"src": name, "tags": ["out"]}), "--count", str(RECORDS), "--rate", "100",
                env=run.env,
            )  # fmt: skip
            assert published.returncode == 0, published.stderr
        for run, name in ((a, "a"), (b, "b")):

            def delivered(folder: Path = tmp_path / name) -> bool:
                return len(lines(folder)) >= RECORDS

            run.wait_until(delivered, 30, f"{name}'s records")
    for name in ("a", "b"):
        sources = [line["src"] for line in lines(tmp_path / name)]
        assert sources == [name] * RECORDS, f"{name} delivered {sources.count('a')} of a's, {sources.count('b')} of b's"
    buffers = sorted(p.relative_to(home) for p in home.rglob("delivery.sqlite3"))
    assert buffers == sorted(
        Path(".local/share/dc/buffer") / f"domain-{run.domain_id}" / "default" / "delivery.sqlite3" for run in (a, b)
    )


def test_a_second_instance_on_the_same_buffer_refuses_to_start_and_names_the_owner(tmp_path: Path) -> None:
    home = tmp_path / "home"
    shared = str(tmp_path / "shared-buffer")
    with Bringup(write_params(tmp_path / "a", shared), home) as a:
        a.wait_ready()
        (owner,) = [
            m.group(1) for line in a.stderr if (m := re.search(r"destination_server active \(pid (\d+)\)", line))
        ]
        with Bringup(write_params(tmp_path / "b", shared), home) as b:
            assert b.wait_exit(60) != 0
        refusal = "\n".join(b.stderr)
        assert f"the delivery buffer {shared}/delivery.sqlite3 is in use by process {owner}" in refusal, refusal
        assert "destination_server.ros__parameters.flb.storage_path" in refusal
        # The first instance is not disturbed.
        published = dc("pub", "/direct", '{"src": "a", "tags": ["out"]}', "--count", "3", "--rate", "50", env=a.env)
        assert published.returncode == 0, published.stderr
        a.wait_until(lambda: len(lines(tmp_path / "a")) >= 3, 30, "a's records")
    assert lines(tmp_path / "b") == []


def _pid_of(run: Bringup, server: str) -> str:
    """The pid a running dc-bringup logged for ``server`` ("<server> active (pid N)")."""
    (pid,) = {m.group(1) for line in run.stderr if (m := re.search(rf"{server} active \(pid (\d+)\)", line))}
    return pid


def _manager_pid(run: Bringup) -> int:
    """The process of a dc-bringup's lifecycle manager: dc-bringup itself, or with --single-process its servers' process."""
    for line in run.stderr:
        if m := re.search(r"DC is up in one process \(pid (\d+)\)", line):
            return int(m.group(1))
    assert run.process is not None
    return run.process.pid


@pytest.mark.usefixtures("bringup_mode")
def test_a_second_instance_in_the_same_domain_and_namespace_stops_naming_the_first_which_runs_on(
    tmp_path: Path,
) -> None:
    home = tmp_path / "home"
    with Bringup(write_params(tmp_path / "a", str(tmp_path / "a-buffer")), home) as a:
        a.wait_ready()
        destination_pid = _pid_of(a, "destination_server")
        configured = sum("destination out (" in line for line in a.stderr)
        same_domain = {"ROS_DOMAIN_ID": str(a.domain_id)}
        started = time.monotonic()
        with Bringup(write_params(tmp_path / "b", str(tmp_path / "b-buffer")), home, env=same_domain) as b:
            code = b.wait_exit(60)
        took = time.monotonic() - started
        assert code != 0
        refusals = [line for line in b.stderr if "another DC runs in ROS domain" in line]
        assert len(refusals) == 1, "\n".join(b.stderr)
        refusal = refusals[0]
        assert f"ROS domain {a.domain_id}, namespace /: " in refusal
        # The process to stop is named: dc-bringup's (its lifecycle manager), or the one of every server.
        assert f"lifecycle_manager_dc (pid {_manager_pid(a)})" in refusal, refusal
        assert "--namespace" in refusal and "ROS_DOMAIN_ID" in refusal
        assert took < 20, f"the second instance took {took:.1f} s to stop"
        assert not any("DC is up" in line for line in b.stderr)
        # The first instance was not touched: no transition reached its servers, and it delivers.
        assert sum("destination out (" in line for line in a.stderr) == configured, "a's destination configured again"
        assert not any("configure" in line and "failed" in line for line in a.stderr), "\n".join(a.stderr)
        active = dc("lifecycle", "is-active", "--timeout", "10", env=a.env)
        assert active.returncode == 0 and active.stdout.startswith("active: servers active"), active.stdout
        published = dc("pub", "/direct", '{"src": "a", "tags": ["out"]}', "--count", "5", "--rate", "50", env=a.env)
        assert published.returncode == 0, published.stderr
        a.wait_until(lambda: len(lines(tmp_path / "a")) >= 5, 30, "a's records after b stopped")
        assert _pid_of(a, "destination_server") == destination_pid
        # In another namespace, both run.
        other = Bringup(
            write_params(tmp_path / "c", str(tmp_path / "c-buffer")),
            home,
            args=["--namespace", "other"],
            env=same_domain,
        )
        with other as c:
            c.wait_ready()
            assert not any("another DC runs" in line for line in c.stderr)
            active = dc("lifecycle", "is-active", "--namespace", "other", "--timeout", "10", env=c.env)
            assert active.returncode == 0, active.stdout + active.stderr
        assert dc("lifecycle", "is-active", "--timeout", "10", env=a.env).returncode == 0
    assert lines(tmp_path / "b") == []
