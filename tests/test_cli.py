"""The `dc` tool and plugin discovery as a user meets them, including a third-party plugin package."""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.cli import STATUS_COLUMNS
from tests.bringup_util import BIN, REPO, dc
from tests.domains import fresh_domain_id
from tests.http_receiver import free_port

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
        (
            "destination_sever:\n  ros__parameters:\n    destination_plugins: []\n"
            "measurement_server:\n  ros__parameters:\n    measurement_plugins: []\n",
            'destination_sever: not a DC server section (did you mean "destination_server"?): it would be ignored',
        ),
    ],
    ids=["invalid-yaml", "unknown-plugin", "wrong-type", "missing-inputs", "misspelled-server"],
)
def test_validate_reports_errors(tmp_path: Path, text: str, expected: str) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(text)
    result = dc("validate", str(params))
    assert result.returncode == 2
    assert expected in result.stderr


UPTIME_GATED = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["uptime"]
    condition_plugins: ["booted", "elsewhere"]
    booted:
      plugin: "dc_conditions/IntegerSuperior"
      key: "{key}"
      value: 10
    elsewhere:
      plugin: "dc_conditions/Exist"
      key: "tme"
      topic: "/dc/measurement/other"
    uptime:
      plugin: "dc_measurements/Uptime"
      if_all_conditions: ["booted", "elsewhere"]
controller_server:
  ros__parameters:
    controller_frequency: 20.0
"""


def test_validate_refuses_a_condition_the_schema_rules_out_and_ignores_other_nodes(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(UPTIME_GATED.format(key="tme"))
    result = dc("validate", str(params))
    assert result.returncode == 2, result.stderr
    assert (
        "measurement_server.booted.key: 'tme': booted could never be active for uptime (the record has no key "
        """'tme' (did you mean "time"?); its keys: time)""" in result.stderr
    )
    params.write_text(UPTIME_GATED.format(key="time"))
    result = dc("validate", str(params))
    assert result.returncode == 0, result.stderr
    assert "elsewhere" not in result.stderr, "a condition on another topic judges that topic's records"
    # Nav2 and other nodes keep their parameters in the same file: ignored, said once, not an error.
    assert "sections for nodes DC does not run, ignored (other nodes' parameters): controller_server" in result.stderr


def test_validate_refuses_a_condition_on_a_field_of_another_type(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(UPTIME_GATED.format(key="time").replace("IntegerSuperior", "BoolEqual").replace("10", "true"))
    result = dc("validate", str(params))
    assert result.returncode == 2, result.stderr
    assert (
        "measurement_server.booted.key: 'time': booted could never be active for uptime (the schema says "
        "integer or number; dc_conditions/BoolEqual needs boolean)" in result.stderr
    )


def test_validate_suggests_a_misspelled_common_parameter(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(UPTIME_GATED.format(key="time").replace("if_all_conditions", "if_all_condition"))
    result = dc("validate", str(params))
    assert result.returncode == 2
    assert (
        "measurement_server.uptime.if_all_condition: unknown parameter of dc_measurements/Uptime (did you mean "
        '"if_all_conditions"?)' in result.stderr
    )


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
def test_every_shipped_configuration_is_valid(
    example: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from dc_bringup.cli import main
    from dc_bringup.local_servers.influxdb import InfluxServer
    from dc_bringup.local_servers.postgres import PostgresServer
    from dc_bringup.local_servers.run import environment
    from dc_bringup.local_servers.seaweedfs import SeaweedS3Server

    (path,) = list((REPO / "params").rglob(example))
    # The storage demos name the local servers' settings as servers.env exports them: those names must exist.
    settings = {
        "postgres": PostgresServer(tmp_path / "pg", port=15432, password="pw").settings(),
        "s3": SeaweedS3Server(tmp_path / "s3", port=18333, secret_key="key").settings(),
        "influxdb": InfluxServer(tmp_path / "influxdb", port=18086).settings(),
    }
    for name, value in environment(settings).items():
        monkeypatch.setenv(name, value)
    # `dc validate`'s own code, in this process: a `dc` process per file cost ~3 s each in imports, and
    # the command line itself (its exit codes, its output) is what the other validate tests run.
    code = main(["validate", str(path)])
    assert code == 0, capsys.readouterr().err


def test_pub_rejects_non_json() -> None:
    result = dc("pub", "/x", "{not json")
    assert result.returncode == 2 and "not JSON" in result.stderr


@pytest.mark.parametrize(
    ("record", "reason"),
    [
        ('{"v": NaN}', "NaN is not a JSON number"),
        ('{"v": -Infinity}', "-Infinity is not a JSON number"),
        ('{"v": 1e999}', "not finite"),
        ('{"t": "\\udcff"}', "lone surrogate \\udcff"),
        ("[1, 2]", "expected a JSON object, got a JSON array"),
    ],
    ids=["nan", "infinity", "overflow", "lone-surrogate", "array"],
)
def test_pub_refuses_what_the_servers_would_count_as_malformed(record: str, reason: str) -> None:
    result = dc("pub", "/x", record)
    assert result.returncode == 2, result.stderr
    assert reason in result.stderr


def test_status_prints_a_table_from_the_metrics_endpoint(tmp_path: Path) -> None:
    import http.server
    import json as _json
    import threading

    document: dict[str, Any] = {
        "destinations": {
            "pg": {
                "received": 10,
                "buffered": 3,
                "buffered_bytes": 600,
                "sent": 7,
                "retried": 2,
                "failed": 2,
                "dropped": 0,
                "dead_lettered": 1,
                "dead_letters": 1,
                "oldest_pending_age_s": 12.5,
                "last_error": "HTTP 503 Service Unavailable",
                "last_error_time": time.time() - 60,
                "last_delivery": time.time() - 3,
                "plugin": {"reconnects": 4},
                "health": {
                    "state": "failing",
                    "since": time.time() - 300,
                    "for_s": 300.0,
                    "reason": "password authentication failed for user dc",
                    "fix": "check the password parameter",
                },
            },
        },
        "buffer": {
            "path": "/b/delivery.sqlite3",
            "storage_sync": "full",
            "quarantined": 1,
            "intake_pending": 0,
            "commit_error": "committing to the buffer: OperationalError: database or disk is full",
            "commit_failing_s": 42.0,
        },
        "intake": {
            "received": 10,
            "malformed": 2,
            "unrouted": {"/t": {"no tags": 3}},
            "untrusted_tags": {"/dc/measurement/map": {"flb_minio": 1}},
        },
        "threads": {"thread_failures": 1, "unhealthy": "thread dc-delivery-writer: RuntimeError: x"},
    }

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            # Times as old as the figures below when dc asks, however long it took to start.
            pg = document["destinations"]["pg"]
            pg["last_error_time"], pg["last_delivery"] = time.time() - 60, time.time() - 3
            pg["health"]["since"] = time.time() - 300
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
        # Its own runtime folder: no server of this session's domain is found running.
        env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
        result = dc("status", "--params", str(params), "--wide", env=env)
        narrow = dc("status", "--params", str(params), env=env)
    finally:
        server.shutdown()
    assert narrow.returncode == 0, narrow.stderr
    assert max(len(line) for line in narrow.stdout.splitlines()) <= 100, narrow.stdout
    narrow_header, narrow_row, error_line, *_ = narrow.stdout.splitlines()
    assert narrow_header.split()[:4] == ["destination", "health", "received", "sent"]
    assert narrow_row.split() == ["pg", "failing", "10", "7", "3", "12.5", "2", "0", "1"]
    assert re.fullmatch(r"  last error: 6\d s ago: HTTP 503 Service Unavailable", error_line), error_line
    assert result.returncode == 0, result.stderr
    header, row, *rest = result.stdout.splitlines()
    titles = header.split()
    assert titles[:4] == ["destination", "health", "received", "buffered"] and "dead-lettered" in titles
    cells = row.split()
    assert cells[:5] == ["pg", "failing", "10", "3", "600"] and "12.5" in cells
    assert titles[-5:] == ["sent", "s", "ago", "last", "error"]
    assert 3.0 <= float(cells[len(STATUS_COLUMNS)]) < 30.0, row  # seconds since last_delivery, the last column
    assert re.search(r"  6\d s ago: HTTP 503 Service Unavailable$", row), row
    assert any("corrupt files set aside 1" in line for line in rest)
    assert any("COMMITS FAILING for 42.0 s" in line and "disk is full" in line for line in rest), rest
    assert any(line.startswith("intake: received 10, malformed 2") for line in rest)
    assert "unrouted: 3 on /t: no tags" in rest
    assert "untrusted tags: 1 on /dc/measurement/map kept from flb_minio (a publisher there is not DC's)" in rest
    assert "pg (its own counters): reconnects 4" in rest
    assert "threads: 1 died, the server is unhealthy: thread dc-delivery-writer: RuntimeError: x" in rest
    assert (
        "destination pg FAILING for 300.0 s: password authentication failed for user dc — check the password parameter"
        in rest
    ), rest
    unreachable = dc("status", "--port", "1")
    assert unreachable.returncode == 1 and "cannot reach" in unreachable.stderr


# Prints each received number as a line; the test freezes it with SIGSTOP after the first one.
SLOW_SUBSCRIBER = """
import rclpy, sys
from rclpy.qos import QoSProfile, ReliabilityPolicy
from dc_interfaces.msg import StringStamped
rclpy.init()
node = rclpy.create_node("slow_subscriber")
node.create_subscription(
    StringStamped, "/acks", lambda m: print(m.data, flush=True), QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
)
print("subscribed", flush=True)
rclpy.spin(node)
"""


class FrozenSubscriber:
    """A subscriber process of /acks, frozen (SIGSTOP) as soon as it has received a first record."""

    LINE_TIMEOUT_S = 30.0

    def __init__(self, env: dict[str, str]) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", SLOW_SUBSCRIBER], env=env, stdout=subprocess.PIPE, text=True
        )
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        assert self._next_line() == "subscribed"

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self._lines.put(line.strip())

    def _next_line(self) -> str:
        try:
            return self._lines.get(timeout=self.LINE_TIMEOUT_S)
        except queue.Empty:
            raise AssertionError(f"the subscriber printed nothing for {self.LINE_TIMEOUT_S} s") from None

    def freeze_at_first_record(self) -> str:
        first = self._next_line()
        self.process.send_signal(signal.SIGSTOP)
        return first

    def thaw_and_read(self, count: int) -> list[str]:
        self.process.send_signal(signal.SIGCONT)
        return [self._next_line() for _ in range(count)]

    def close(self) -> None:
        self.process.send_signal(signal.SIGCONT)
        self.process.kill()
        self.process.wait()


@pytest.fixture
def ros_env() -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(fresh_domain_id())
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


def start_dc_pub(env: dict[str, str], count: int, linger_s: float) -> subprocess.Popen[str]:
    """`dc pub` of ``count`` records ``{"n": 1}`` on /acks, 20 a second."""
    return subprocess.Popen(
        [str(BIN / "dc"), "pub", "/acks", '{"n": 1}', "--count", str(count), "--rate", "20", "--linger", str(linger_s)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_pub_exits_only_once_a_slow_subscriber_has_every_record(ros_env: dict[str, str]) -> None:
    subscriber = FrozenSubscriber(ros_env)
    try:
        pub = start_dc_pub(ros_env, count=10, linger_s=120)
        assert subscriber.freeze_at_first_record() == '{"n": 1}'
        # Frozen while dc pub publishes the other nine (0.45 s) and well after: it cannot acknowledge them.
        with pytest.raises(subprocess.TimeoutExpired):
            pub.wait(2.0)
        received = subscriber.thaw_and_read(9)
        # It returns on the acknowledgement, not at the end of --linger.
        out, err = pub.communicate(timeout=60)
    finally:
        subscriber.close()
    assert pub.returncode == 0, err
    assert received == ['{"n": 1}'] * 9
    assert "published 10 record(s) on /acks" in out


def test_pub_of_stdin_publishes_one_record_a_line_in_order(ros_env: dict[str, str]) -> None:
    subscriber = FrozenSubscriber(ros_env)
    try:
        lines = '{"n": 1}\n\n{"n": 2}\n{"n": 3, "s": "x y"}\n'  # a blank line is no record
        pub = subprocess.run(
            [str(BIN / "dc"), "pub", "/acks", "-", "--rate", "0"],
            env=ros_env, input=lines, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        received = subscriber.thaw_and_read(3)
    finally:
        subscriber.close()
    assert pub.returncode == 0, pub.stderr
    assert received == ['{"n": 1}', '{"n": 2}', '{"n": 3, "s": "x y"}']
    assert "published 3 record(s) on /acks" in pub.stdout


def test_pub_answers_on_stdout_and_fast_dds_own_lines_go_to_stderr(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A Fast DDS profile file it cannot parse makes the middleware print its errors from C++ on
    descriptor 1; a script reading `dc pub`'s answer reads that answer alone."""
    profile = tmp_path / "broken_profile.xml"
    profile.write_text("<dds><profiles><unclosed>")
    result = subprocess.run(
        [str(BIN / "dc"), "pub", "/x", '{"n": 1}', "--no-wait"],
        env={**ros_env, "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)},
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["published 1 record(s) on /x"]
    assert "XMLPARSER" in result.stderr and str(profile) in result.stderr


@pytest.mark.parametrize(
    ("stdin", "args", "said"),
    [
        ('{"n": 1}\n{"n": NaN}\n', [], "refused, not JSON that DC carries (stdin line 2): NaN is not a JSON number"),
        ("\n\n", [], "no record on stdin"),
        ('{"n": 1}\n', ["--count", "3"], "--count repeats one record"),
    ],
    ids=["malformed-line", "empty", "count"],
)
def test_pub_of_stdin_refuses_every_record_when_one_line_is_wrong(stdin: str, args: list[str], said: str) -> None:
    result = subprocess.run(
        [str(BIN / "dc"), "pub", "/x", "-", "--no-wait", *args], input=stdin, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and said in result.stderr, result.stderr
    assert "published" not in result.stdout


def test_pub_says_when_a_subscriber_did_not_acknowledge_within_linger(ros_env: dict[str, str]) -> None:
    subscriber = FrozenSubscriber(ros_env)
    try:
        pub = start_dc_pub(ros_env, count=3, linger_s=1)
        subscriber.freeze_at_first_record()
        out, err = pub.communicate(timeout=30)
    finally:
        subscriber.close()
    assert pub.returncode == 1
    assert "had not acknowledged every record after 1.0 s" in err
    assert "published 3 record(s) on /acks" in out


def test_validate_warns_when_two_servers_would_serve_metrics_on_one_port(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text("""
measurement_server:
  ros__parameters:
    http_server: true
    http_listen: 0.0.0.0
    measurement_plugins: ["uptime"]
    uptime:
      plugin: "dc_measurements/Uptime"
group_server:
  ros__parameters:
    groups: []
    http_server: true
    http_port: 2022
""")
    result = dc("validate", str(params))
    assert result.returncode == 0, result.stderr
    assert (
        "measurement_server.http_port: 2022 is also group_server.http_port: measurement_server serves its metrics"
        " on another, free port (dc status finds it)" in result.stderr
    )


def test_pub_with_nobody_subscribed_says_so_and_fails_unless_no_wait(ros_env: dict[str, str]) -> None:
    alone = dc("pub", "/nobody_listens", '{"n": 1}', "--wait-matched", "0.5", env=ros_env)
    assert alone.returncode == 3, alone.stdout + alone.stderr
    assert "nobody subscribes to /nobody_listens (waited 0.5 s); nothing published" in alone.stderr
    assert "published" not in alone.stdout
    anyway = dc("pub", "/nobody_listens", '{"n": 1}', "--no-wait", env=ros_env)
    assert anyway.returncode == 0, anyway.stderr
    assert "published 1 record(s) on /nobody_listens" in anyway.stdout


def test_status_params_reads_a_file_whose_secret_is_not_set_in_this_shell(tmp_path: Path) -> None:
    params = tmp_path / "p.yaml"
    params.write_text(
        "destination_server:\n  ros__parameters:\n    flb:\n      http_server: true\n"
        f"      http_port: {free_port()}\n    destination_plugins: [web]\n"
        '    web:\n      plugin: dc_destinations/HTTP\n      inputs: ["/x"]\n'
        '      http_user: dc\n      http_passwd: "${DC_TEST_PASSWORD_NOT_IN_THIS_SHELL}"\n'
    )
    env = {k: v for k, v in os.environ.items() if k != "DC_TEST_PASSWORD_NOT_IN_THIS_SHELL"}
    result = dc("status", "--params", str(params), env=env)
    # It went on to ask the server (none listens here), instead of failing on the variable.
    assert result.returncode == 1 and "cannot reach destination_server" in result.stderr, result.stderr
    assert "not set in this shell, shown as unset: DC_TEST_PASSWORD_NOT_IN_THIS_SHELL" in result.stderr
