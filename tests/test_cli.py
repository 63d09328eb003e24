"""The `dc` tool and plugin discovery as a user meets them, including a third-party plugin package."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.bringup_util import REPO, dc

PLUGIN_SRC = REPO / "tests" / "data" / "dc_example_plugin"


@pytest.fixture(scope="module")
def third_party_env(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """A real install of a separate package into its own folder: DC only sees its entry point."""
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(PLUGIN_SRC),
        ],
        check=True,
        capture_output=True,
        cwd=build,
    )
    env = dict(os.environ)
    env["PYTHONPATH"] = str(target)
    return env


def test_list_plugins_shows_builtins_with_descriptions() -> None:
    result = dc("list-plugins")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert any(line.split()[:1] == ["dc_measurements/Uptime"] and "booted" in line for line in lines)
    assert any(line.strip().startswith("dc_destinations/FlbStdout") for line in lines)
    assert "conditions:" in lines and "destinations:" in lines


def test_list_plugins_of_one_kind_with_parameters() -> None:
    result = dc("list-plugins", "measurements", "--params")
    assert result.returncode == 0
    assert "destinations:" not in result.stdout
    assert "record (string, default" in result.stdout


def test_third_party_plugin_is_listed_and_loaded(third_party_env: dict[str, str], tmp_path: Path) -> None:
    listed = dc("list-plugins", "measurements", env=third_party_env)
    assert "dc_example_plugin/Answer" in listed.stdout
    assert "third-party package" in listed.stdout and "[dc-example-plugin]" in listed.stdout
    params = tmp_path / "p.yaml"
    params.write_text(
        "measurement_server:\n  ros__parameters:\n    measurement_plugins: [answer]\n"
        "    answer:\n      plugin: dc_example_plugin/Answer\n      answer: 41\n"
    )
    assert dc("validate", str(params), env=third_party_env).returncode == 0
    without = dc("validate", str(params))
    assert without.returncode == 2 and "unknown measurement plugin 'dc_example_plugin/Answer'" in without.stderr


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("measurement_server:\n  ros__parameters:\n    measurement_plugins: [u\n", "invalid YAML at line"),
        (
            "measurement_server:\n  ros__parameters:\n    measurement_plugins: [u]\n    u:\n      plugin: dc_measurements/Nope\n",
            "measurement_server.u.plugin: unknown measurement plugin",
        ),
        (
            "measurement_server:\n  ros__parameters:\n    measurement_plugins: [u]\n    u:\n      plugin: dc_measurements/Uptime\n"
            "      polling_interval: fast\n",
            'measurement_server.u.polling_interval: expected an integer, got "fast"',
        ),
        (
            "destination_server:\n  ros__parameters:\n    destination_plugins: [o]\n    o:\n      plugin: dc_destinations/Stdout\n",
            "destination_server.o.inputs: required parameter missing",
        ),
    ],
    ids=["invalid-yaml", "unknown-plugin", "wrong-type", "missing-inputs"],
)
def test_validate_reports_errors(tmp_path: Path, text: str, expected: str) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(text)
    result = dc("validate", str(params))
    assert result.returncode == 2
    assert expected in result.stderr


def test_validate_warns_about_dangling_inputs_and_unknown_tags(tmp_path: Path) -> None:
    result = dc("validate", str(REPO / "params/examples/example_6.yaml"))
    assert result.returncode == 0
    assert "/dc/measurement/string_stamped is published by nothing" in result.stderr
    assert 'did you mean "/dc/measurement/my_string_stamped"' in result.stderr
    params = tmp_path / "p.yaml"
    params.write_text(
        (REPO / "params/examples/example_1.yaml").read_text().replace('tags: ["flb_stdout"]', 'tags: ["flb_stdot"]')
    )
    result = dc("validate", str(params))
    assert (
        "measurement_server.uptime.tags: 'flb_stdot' names no destination (did you mean \"flb_stdout\"?)"
        in result.stderr
    )


@pytest.mark.parametrize("example", sorted(p.name for p in (REPO / "params").rglob("*.yaml")))
def test_every_shipped_configuration_is_valid(example: str) -> None:
    (path,) = list((REPO / "params").rglob(example))
    result = dc("validate", str(path))
    assert result.returncode == 0, result.stderr


def test_pub_rejects_non_json() -> None:
    result = dc("pub", "/x", "{not json")
    assert result.returncode == 2 and "not JSON" in result.stderr


def test_status_prints_a_table_from_the_metrics_endpoint(tmp_path: Path) -> None:
    import http.server
    import json as _json
    import threading

    document = {
        "destinations": {
            "pg": {"received": 10, "buffered": 3, "buffered_bytes": 600, "sent": 7, "retried": 2, "failed": 2,
                   "dropped": 0, "dead_lettered": 1, "dead_letters": 1, "oldest_pending_age_s": 12.5,
                   "last_error": "HTTP 503 Service Unavailable"},
        },
        "buffer": {"path": "/b/delivery.sqlite3", "storage_sync": "full", "quarantined": 1, "intake_pending": 0},
        "intake": {"received": 10, "malformed": 2},
    }

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = _json.dumps(document).encode()
            self.send_response(200 if self.path == "/api/v1/metrics" else 404)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        params = tmp_path / "p.yaml"
        params.write_text(
            "destination_server:\n  ros__parameters:\n    flb:\n      http_server: true\n"
            f"      http_port: {server.server_address[1]}\n    destination_plugins: []\n"
        )
        result = dc("status", "--params", str(params))
    finally:
        server.shutdown()
    assert result.returncode == 0, result.stderr
    header, row, *rest = result.stdout.splitlines()
    titles = header.split()
    assert titles[:3] == ["destination", "received", "buffered"] and "dead-lettered" in titles
    cells = row.split()
    assert cells[:4] == ["pg", "10", "3", "600"] and "12.5" in cells
    assert row.endswith("HTTP 503 Service Unavailable")
    assert any("corrupt files set aside 1" in line for line in rest)
    assert any(line.startswith("intake: received 10, malformed 2") for line in rest)
    unreachable = dc("status", "--port", "1")
    assert unreachable.returncode == 1 and "cannot reach" in unreachable.stderr
