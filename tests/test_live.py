"""`dc top`, `dc tap` and `dc status` against a running dc-bringup: what an operator sees at a terminal.

The metrics endpoints are on by default: the default job and a second DC on the same machine (another
ROS domain) are asked without editing their parameter files.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any

import pytest

from tests.bringup_util import BIN, REPO, Bringup, dc

WIDTH = 100

FAST_UPTIME = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["uptime"]
    uptime:
      plugin: "dc_measurements/Uptime"
      polling_interval: 200
      tags: ["stdout"]
destination_server:
  ros__parameters:
    flb:
      flush: 0.2
    destination_plugins: ["stdout"]
    stdout:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/uptime"]
"""


def env_of(run: Bringup) -> dict[str, str]:
    return {**run.env, "COLUMNS": "200"}  # a wide terminal must not widen the narrow views


def json_objects(text: str) -> list[Any]:
    decoder, at = json.JSONDecoder(), 0
    found: list[Any] = []
    while True:
        while at < len(text) and text[at].isspace():
            at += 1
        if at >= len(text):
            return found
        try:
            value, at = decoder.raw_decode(text, at)
        except ValueError as exc:
            raise AssertionError(f"not JSON at {at}: {text!r}") from exc
        found.append(value)


@pytest.mark.e2e
def test_top_and_status_on_the_default_job_fit_100_columns(tmp_path: Path) -> None:
    with Bringup(REPO / "params" / "default.yaml", tmp_path / "home") as run:
        run.wait_records(1, timeout=40, predicate=lambda r: r.get("name") == "cpu")
        run.wait_until(lambda: len({r.get("name") for r in run.records()}) >= 6, 40, "a record of each measurement")

        top = dc("top", "--once", "--interval", "1", env=env_of(run))
        assert top.returncode == 0, top.stderr
        lines = top.stdout.splitlines()
        assert max(len(line) for line in lines) <= WIDTH, top.stdout
        rows = {line.split()[0]: line.split() for line in lines[1:] if line.strip()}
        assert rows["measurement"][:3] == ["measurement", "state", "rec/s"]
        for name in ("cpu", "memory", "storage", "uptime", "os", "network"):
            assert int(rows[name][3]) >= 1, top.stdout  # published
            assert re.fullmatch(r"\d+\.\d\d", rows[name][2]), top.stdout  # records/s over the interval
        assert rows["destination"][:5] == ["destination", "state", "in/s", "sent/s", "pending"]
        for name in ("stdout", "file"):
            assert rows[name][1] == "ok" and re.fullmatch(r"\d+\.\d\d", rows[name][2]), top.stdout

        # Not a terminal: no screen clearing, one table after the other, each interval.
        try:
            subprocess.run(
                [str(BIN / "dc"), "top", "--interval", "0.5"], capture_output=True, env=env_of(run), timeout=4
            )
            raise AssertionError("dc top without --once exited")
        except subprocess.TimeoutExpired as running_top:
            shown = (running_top.stdout or b"").decode()
        assert shown.count("dc top ") >= 2 and "\x1b[" not in shown, shown

        status = dc("status", env=env_of(run))
        assert status.returncode == 0, status.stderr
        narrow = status.stdout.splitlines()
        assert max(len(line) for line in narrow) <= WIDTH, status.stdout
        assert not [line for line in narrow if line.strip() in ("hop:", "hop: ")], status.stdout
        assert any(line.split()[:2] == ["file", "ok"] for line in narrow)
        assert any(line.split()[:1] == ["uptime"] for line in narrow)
        wide = dc("status", "--wide", env=env_of(run))
        assert wide.returncode == 0, wide.stderr
        assert max(len(line) for line in wide.stdout.splitlines()) > WIDTH
        assert "dead-lettered" in wide.stdout and "dead-lettered" not in status.stdout
        # The same, only the servers of the file: no edit of it needed.
        with_params = dc("status", "--params", str(REPO / "params" / "default.yaml"), env=env_of(run))
        assert with_params.returncode == 0, with_params.stderr
        assert with_params.stdout.splitlines()[0] == narrow[0]


@pytest.mark.e2e
def test_tap_prints_records_as_they_pass(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(FAST_UPTIME)
    with Bringup(params, tmp_path / "home") as run:
        run.wait_records(1, timeout=40)
        tap = dc("tap", "uptime", "--count", "3", env=env_of(run), timeout=30)
        assert tap.returncode == 0, tap.stderr
        records = json_objects(tap.stdout)
        assert len(records) == 3 and all(r["name"] == "uptime" and r["time"] >= 0 for r in records), tap.stdout
        assert '\n  "name": "uptime"' in tap.stdout  # pretty-printed, a key a line

        # A destination's inputs, from the parameter file; a filter that matches and one that does not.
        by_destination = dc(
            "tap", "stdout", "--params", str(params), "--count", "2", "--filter", "name=uptime", env=env_of(run)
        )
        assert by_destination.returncode == 0, by_destination.stderr
        assert [r["name"] for r in json_objects(by_destination.stdout)] == ["uptime", "uptime"]
        assert "/dc/measurement/uptime" in by_destination.stderr

    # Stopped: its servers' addresses are gone with them; no guess at another DC's port.
    stopped = dc("status", env=env_of(run))
    assert stopped.returncode == 1 and stopped.stdout == ""
    assert "dc status: no running DC server found in " in stopped.stderr

    nobody = dc("tap", "/dc/measurement/nothing_here", "--timeout", "1", env=env_of(run))
    assert nobody.returncode == 1
    assert nobody.stdout == ""
    assert nobody.stderr.strip().splitlines() == [
        "dc tap: no publisher on /dc/measurement/nothing_here after 1 s (is dc-bringup running, in this ROS domain"
        " and --namespace?)"
    ]


@pytest.mark.e2e
def test_a_second_dc_on_the_machine_serves_its_metrics_on_free_ports(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(FAST_UPTIME)
    with Bringup(params, tmp_path / "first") as first:
        first.wait_records(1, timeout=40)
        with Bringup(params, tmp_path / "second") as second:
            second.wait_records(1, timeout=40)
            ports = []
            for run in (first, second):
                status = dc("status", "--json", env=env_of(run))
                assert status.returncode == 0, status.stderr
                documents = json.loads(status.stdout)
                assert set(documents) == {"destination_server", "measurement_server"}
                assert documents["measurement_server"]["measurements"]["uptime"]["published"] >= 1
                served = re.findall(r"metrics HTTP server on http://127\.0\.0\.1:(\d+)/", "\n".join(run.stderr))
                # A server that did not get its default port (held by the other DC, or by another test's DC
                # that may have let it go since) said so: a warning, not a failure.
                for port in set(served) - {"2020", "2022"}:
                    run.wait_stderr(f"is taken (another DC on this machine?); serving on 127.0.0.1:{port} instead")
                ports.append(served)
            assert len(ports[0]) == len(ports[1]) == 2 and not set(ports[0]) & set(ports[1]), ports


def test_a_server_address_is_found_while_its_process_lives(tmp_path: Path, monkeypatch: Any) -> None:
    from dc_core import metrics_registry as registry

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    own = registry.announce("measurement_server", 7, "/r1", "127.0.0.1", 40123)
    assert own is not None and own.parent.stat().st_mode & 0o777 == 0o700
    # A server killed with SIGKILL leaves its file: a pid no process has is skipped.
    gone = own.parent / "group_server.json"
    gone.write_text(json.dumps({"server": "group_server", "host": "127.0.0.1", "port": 40124, "pid": 2**22 + 1}))
    found = registry.announced(7, "r1")
    assert list(found) == ["measurement_server"] and found["measurement_server"].port == 40123
    assert registry.announced(7, "/") == {} and registry.announced(8, "/r1") == {}
    registry.withdraw(own)
    assert registry.announced(7, "/r1") == {}


def test_status_targets_for_every_shipped_parameter_file(tmp_path: Path, monkeypatch: Any) -> None:
    """`dc status --params` with any params/ file, none edited: the running servers' addresses, also
    for a file that names a secret's variable only the servers' environment has."""
    from dc_bringup.live import metrics_targets
    from dc_core import metrics_registry as registry

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    for name in ("destination_server", "group_server", "measurement_server"):
        registry.announce(name, 7, "/", "127.0.0.1", 40000 + len(name))
    files = sorted(p for p in (REPO / "params").rglob("*.yaml") if "fastdds" not in p.parts)
    assert len(files) > 20
    for file in files:
        targets = metrics_targets(str(file), "", "127.0.0.1", None)
        assert targets and all(t.port >= 40000 for t in targets), (file, targets)


def test_an_ipv6_metrics_address_is_bracketed_in_the_url() -> None:
    from dc_bringup.live import Target

    assert Target("destination_server", "::1", 2022).url == "http://[::1]:2022/api/v1/metrics"
    assert Target("", "127.0.0.1", 2020).url == "http://127.0.0.1:2020/api/v1/metrics"
