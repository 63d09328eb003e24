"""InfluxDB destination: the line protocol DC writes, delivery to a real influxd (v1 API), the v2 request, an outage.

The v1 tests run against Debian's influxd 1.6 started by a module fixture (skipped when it is not
installed). No InfluxDB 2.x server installs here (and 1.6 has no /api/v2/write), so the v2 tests
check the request a local HTTP receiver gets. The last tests go through `dc-bringup`.
"""

from __future__ import annotations

import base64
import gzip
import logging
import re
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.influxdb import InfluxServer, missing_reason
from dc_core.destination import OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.influxdb import InfluxDB, InfluxDBParams, Sequencer, to_point
from dc_destinations.record_ids import new_record_id
from tests.bringup_util import BIN, Bringup
from tests.destination_helpers import forwarding_params, through_pipeline, tls_refused
from tests.http_receiver import Receiver, Request
from tests.tls_pki import KEY_PASSWORD, Pki, make_pki

STAMP = 1_677_668_906_045_817_123
needs_influxd = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))


def influx(**params: Any) -> InfluxDB:
    logger: RecordingLogger | None = params.pop("logger", None)
    plugin = InfluxDB(
        FakeContext(name="tsdb", logger=logger or RecordingLogger()), parse_params(InfluxDBParams, params, "x")
    )
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def record(data: dict[str, Any], stamp_ns: int = STAMP, record_id: str = "") -> OutgoingRecord:
    rid = record_id or new_record_id()
    return OutgoingRecord(rid, "/dc/measurement/cpu", stamp_ns, {**data, "record_id": rid})


def line(data: dict[str, Any], stamp_ns: int = STAMP, **params: Any) -> str:
    rec = OutgoingRecord("r1", "/dc/measurement/cpu", stamp_ns, data)
    return to_point(rec, parse_params(InfluxDBParams, params, "x")).line()


# -- line protocol ----------------------------------------------------------------------------------


def test_scalar_fields_and_the_exact_nanosecond_stamp() -> None:
    text = line({"name": "cpu", "n": 3, "x": 0.5, "whole": 2.0, "ok": True, "no": False, "s": "hi"}, STAMP)
    assert text == f'dc_cpu n=3i,x=0.5,whole=2.0,ok=true,no=false,s="hi" {STAMP}'


def test_every_special_character_is_escaped() -> None:
    data = {
        "name": "my cpu,1=x",
        "host": "a b,c=d",
        "k ey,=": 'say "hi" \\ there\nline two',
    }
    text = line(data, 5, tag_keys=["host"])
    assert text == "dc_my\\ cpu\\,1=x,host=a\\ b\\,c\\=d k\\ ey\\,\\==" + '"say \\"hi\\" \\\\ there\nline two" 5'


def test_nested_objects_and_arrays_are_flattened_and_nulls_skipped() -> None:
    data = {"name": "cpu", "cpu": {"average": 1.5, "per": [1, 2]}, "sorted": [{"pid": 7}], "none": None, "e": {}}
    assert line(data, 1) == "dc_cpu cpu.average=1.5,cpu.per.0=1i,cpu.per.1=2i,sorted.0.pid=7i 1"
    assert line(data, 1, separator="_").startswith("dc_cpu cpu_average=1.5,cpu_per_0=1i")


def test_tags_auto_tags_measurement_parameter_and_the_time_key() -> None:
    data = {"name": "cpu", "robot": "c3po", "run": 4, "load": 0.5, "time": 9, "record_id": "id1"}
    assert line(data, 1, tag_keys="robot run") == "dc_cpu,robot=c3po,run=4 load=0.5,time_=9i 1"
    kept = line(data, 1, auto_tags=True, bookkeeping_fields=True)
    assert kept == 'dc_cpu,robot=c3po run=4i,load=0.5,time_=9i,record_id="id1" 1', (
        "record_id stays a field: a tag per record would make a series per record"
    )
    assert line(data, 1, measurement="robots").startswith('robots name="cpu",robot="c3po"')
    no_name = OutgoingRecord("r", "/dc/measurement/uptime", 1, {"v": 1})
    assert to_point(no_name, parse_params(InfluxDBParams, {}, "x")).line() == "dc_uptime v=1i 1"


def test_records_that_cannot_be_points_are_rejected_alone() -> None:
    dest = influx(port=1, tag_keys=["tag"], measurement_prefix="")  # "#cpu" as the measurement: a comment line
    batch = [
        OutgoingRecord("r0", "/dc/measurement/cpu", 1, {"name": "cpu", "v": None, "tag": "x", "e": []}),
        record({"name": "cpu", "v": 1}),
        record({"name": "cpu", "big": 2**70}),
        record({"name": "#cpu", "v": 1}),
        record({"name": "cpu", "bad\\ key": 1}),
    ]
    lines, rejected = dest.lines(batch)
    assert list(lines) == [1]
    assert rejected[0] == "the record has no field InfluxDB can store (every value is a tag, null or empty)"
    assert "64-bit" in rejected[2] and "comment" in rejected[3] and "backslash" in rejected[4]


def test_sequence_tag_separates_simultaneous_records_and_stays_on_retry() -> None:
    dest = influx(port=1)
    a, b, c = (record({"name": "cpu", "v": i}, stamp_ns=7) for i in range(3))
    lines, _ = dest.lines([a, b, c])
    assert [text.split(" ")[0] for text in lines.values()] == ["dc_cpu", "dc_cpu,_seq=1", "dc_cpu,_seq=2"]
    again, _ = dest.lines([b])
    assert again[0].startswith("dc_cpu,_seq=1 "), "a retried record keeps its number"
    sequencer = Sequencer()
    point = to_point(a, parse_params(InfluxDBParams, {}, "x"))
    assert [sequencer.number(point, rid) for rid in ("x", "y", "x")] == [0, 1, 0]
    off, _ = influx(port=1, sequence_tag="").lines([a, b])
    assert all(text.startswith("dc_cpu v=") for text in off.values())


def test_secret_parameters_and_alias() -> None:
    assert {p.name for p in describe_params(InfluxDBParams) if p.secret} == {
        "http_passwd",
        "http_token",
        "tls_key_passwd",
    }
    p = parse_params(InfluxDBParams, {"http_user": "u", "http_password": "pw"}, "x")
    assert p.http_passwd == "pw" and "pw" not in repr(p)
    assert parse_params(InfluxDBParams, {"bucket": "b"}, "x").api_version == "v2"
    assert parse_params(InfluxDBParams, {}, "x").api_version == "v1"


# -- shaped as Telegraf users expect --------------------------------------------------------------------

FLATTENED: dict[str, Any] = {
    "date": "2026-03-01T03:30:00.000Z",
    "name": "cpu",
    "/average": 12.5,
    "/sorted/0/cmd": "python3 worker.py --token s3cr3t-" + "x" * 80,
    "/sorted/0/pid": 42,
    "/sorted/0/user": "robot",
    "flattened": True,
    "run_id": "12",
    "robot_name": "c3po",
    "record_id": "0190d1e6-aaaa-7000-8000-000000000001",
}


def test_points_are_shaped_as_telegraf_users_expect() -> None:
    """Dotted field names without the leading /, no bookkeeping, run_id a field, the command line cut,
    the measurement prefixed; auto_tags tags the robot, never the date, the run or a flattened value."""
    cmd = FLATTENED["/sorted/0/cmd"]
    assert line(FLATTENED, 1, tag_keys=["robot_name"], auto_tags=True) == (
        'dc_cpu,robot_name=c3po average=12.5,sorted.0.cmd="' + cmd[:64] + '…",sorted.0.pid=42i,'
        'sorted.0.user="robot",run_id="12" 1'
    )
    assert "sorted.0.cmd" not in line(FLATTENED, 1, command_line_chars=0), "command lines dropped"
    assert f'sorted.0.cmd="{cmd}"' in line(FLATTENED, 1, command_line_chars=-1), "whole, as the original"


def test_the_originals_points_stay_reachable_by_options() -> None:
    original = line(
        FLATTENED,
        1,
        measurement_prefix="",
        pointer_field_names=True,
        bookkeeping_fields=True,
        command_line_chars=-1,
        tag_keys=["run_id"],
    )
    assert original.startswith('cpu,run_id=12 date="2026-03-01T03:30:00.000Z",/average=12.5,/sorted/0/cmd="python3')
    assert original.endswith(',flattened=true,robot_name="c3po",record_id="0190d1e6-aaaa-7000-8000-000000000001" 1')


@pytest.mark.parametrize("prefix", ["dc cpu_", "#dc_", "a,b", 'q"', "x\\ "])
def test_a_measurement_prefix_line_protocol_or_a_query_cannot_take_is_a_configure_error(prefix: str) -> None:
    with pytest.raises(ConfigError, match=r"x\.measurement_prefix: expected the start of a measurement name"):
        parse_params(InfluxDBParams, {"measurement_prefix": prefix}, "x")
    with pytest.raises(ConfigError, match=r"x\.content_encoding"):
        parse_params(InfluxDBParams, {"content_encoding": "br"}, "x")


# -- v1 against a real influxd ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InfluxServer]:
    if missing_reason() is not None:
        pytest.skip(str(missing_reason()))
    with InfluxServer(tmp_path_factory.mktemp("influx"), database="dc") as s:
        yield s


def rows(server: InfluxServer, query: str) -> list[dict[str, Any]]:
    (result,) = server.query(query, database=server.database)
    out = []
    for series in result.get("series", []):  # type: ignore[attr-defined]
        for values in series["values"]:
            row = dict(zip(series["columns"], values, strict=True))
            out.append({"_measurement": series["name"], **series.get("tags", {}), **row})
    return out


@needs_influxd
def test_v1_points_arrive_with_fields_tags_and_time(server: InfluxServer) -> None:
    dest = influx(**server.settings(), tag_keys=["robot"], bookkeeping_fields=True)
    batch = [
        record({"name": "arrive", "robot": "c3po", "cpu": {"average": 1.5}, "n": 3, "s": 'q"\\', "ok": True}, 11),
        record({"name": "arrive", "robot": "r2d2", "cpu": {"average": 2.5}, "n": 4, "s": "x", "ok": False}, 12),
    ]
    assert dest.send(batch) is None
    got = rows(server, "SELECT * FROM dc_arrive")
    assert [(r["time"], r["robot"], r["cpu.average"], r["n"], r["s"], r["ok"]) for r in got] == [
        (11, "c3po", 1.5, 3, 'q"\\', True),
        (12, "r2d2", 2.5, 4, "x", False),
    ]
    assert [r["record_id"] for r in got] == [r.record_id for r in batch]


HOUR_NS = 3600 * 10**9
T0 = 1_772_323_200 * 10**9  # 2026-03-01T00:00:00Z


def grafana(query: str, start_ns: int, end_ns: int, interval: str) -> str:
    """A query of the page as Grafana sends it: $timeFilter and $__interval filled in."""
    return query.replace("$timeFilter", f"time >= {start_ns} AND time < {end_ns}").replace("$__interval", interval)


@needs_influxd
def test_the_pages_grafana_queries_answer_from_dc_points_beside_telegrafs(server: InfluxServer) -> None:
    """The InfluxQL of the page, against a real influxd written to with gzip (the default): DC's cpu
    beside Telegraf's in one database, two robots, two runs."""
    dest = influx(**server.settings(), tag_keys=["robot_name"])
    batch = [
        record({**FLATTENED, "robot_name": robot, "run_id": run, "/average": load}, T0 + n * 1200 * 10**9)
        for robot, offset in (("c3po", 0.0), ("r2d2", 50.0))
        for n, (run, load) in enumerate((("9", 10.0 + offset), ("9", 20.0 + offset), ("10", 30.0 + offset)))
    ]
    assert dest.send(batch) is None
    # What Telegraf's inputs.cpu writes to the same database: cpu,cpu=cpu-total,host=c3po usage_idle=99.0
    telegraf = influx(**server.settings(), measurement="cpu", tag_keys=["cpu", "host"])
    assert telegraf.send([record({"cpu": "cpu-total", "host": "c3po", "usage_idle": 99.0}, T0)]) is None
    page = (Path(__file__).parent / "README.md").read_text()
    queries = re.findall(r"```sql\n(.*?)\n```", page, re.DOTALL)
    assert len(queries) == 4, "the page's Grafana queries"
    span = (T0, T0 + HOUR_NS)
    mean = rows(server, grafana(queries[0], *span, "30m"))
    assert [(r["time"], r["robot_name"], r["mean"]) for r in mean if r["mean"] is not None] == [
        (T0, "c3po", 15.0),
        (T0 + HOUR_NS // 2, "c3po", 30.0),
        (T0, "r2d2", 65.0),
        (T0 + HOUR_NS // 2, "r2d2", 80.0),
    ]
    p95 = rows(server, grafana(queries[1], *span, "1h"))
    assert {(r["robot_name"], r["p95"]) for r in p95} == {("c3po", 30.0), ("r2d2", 80.0)}
    runs = rows(server, grafana(queries[2], *span, "1h"))
    assert {(r["robot_name"], r["runs"]) for r in runs} == {("c3po", 2), ("r2d2", 2)}, "run_id a field: no series"
    robots = rows(server, queries[3])
    assert {r["value"] for r in robots} == {"c3po", "r2d2"}
    measurements = {r["name"] for r in rows(server, "SHOW MEASUREMENTS")}
    assert {"cpu", "dc_cpu"} <= measurements, "Telegraf's cpu and DC's side by side"
    assert {r["fieldKey"] for r in rows(server, "SHOW FIELD KEYS FROM dc_cpu")} == {
        "average",
        "run_id",
        "sorted.0.cmd",
        "sorted.0.pid",
        "sorted.0.user",
    }, "no date, flattened or record_id field"


@needs_influxd
def test_v1_a_field_type_conflict_rejects_only_that_record(server: InfluxServer) -> None:
    dest = influx(**server.settings())
    assert dest.send([record({"name": "conflict", "v": 1}, 1)]) is None
    batch = [record({"name": "conflict", "v": i}, 10 + i) for i in range(4)]
    batch[2] = record({"name": "conflict", "v": "text"}, 12)
    outcome = dest.send(batch)
    assert isinstance(outcome, SendOutcome) and not outcome.retry and list(outcome.reject) == [2]
    assert (
        "field type conflict" in outcome.reject[2]
        and 'input field "v" on measurement "dc_conflict"' in (outcome.reject[2])
    )
    assert outcome.reject[2].startswith("HTTP 400 Bad Request: partial write")
    assert [r["time"] for r in rows(server, "SELECT v FROM dc_conflict")] == [1, 10, 11, 13]


@needs_influxd
def test_v1_an_unnamed_refusal_is_isolated_line_by_line(server: InfluxServer) -> None:
    dest = influx(**server.settings())
    batch = [record({"name": "iso", "v": 1}, 1), record({"name": "iso", "v": 2}, 2)]
    writes: list[int] = []
    original = dest._write

    def first_refused(lines: list[str]) -> tuple[int, str]:
        writes.append(len(lines))
        if len(lines) > 1:
            return 400, "HTTP 400 Bad Request: something InfluxDB did not explain"
        return original(lines)

    dest._write = first_refused  # type: ignore[method-assign]
    assert dest.send(batch) is None
    assert writes == [2, 1, 1]
    assert [r["v"] for r in rows(server, "SELECT v FROM dc_iso")] == [1, 2]


@needs_influxd
def test_v1_missing_database_is_retryable_and_named(server: InfluxServer) -> None:
    dest = influx(host="127.0.0.1", port=server.port, database="nowhere")
    with pytest.raises(RetryableError, match="InfluxDB database 'nowhere' not found: HTTP 404"):
        dest.send([record({"name": "x", "v": 1})])


PASSWORD = "hunter2-Very-Secret"


@needs_influxd
def test_v1_auth_wrong_password_is_retryable_and_never_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_influxdb.secret")
    with InfluxServer(tmp_path / "auth", database="secure", user="admin", password=PASSWORD) as secured:
        settings = secured.settings()
        wrong = influx(logger=logger, **{**settings, "http_passwd": "not-" + PASSWORD})
        with pytest.raises(RetryableError) as caught:
            wrong.send([record({"name": "a", "v": 1})])
        message = str(caught.value)
        assert message.startswith("InfluxDB refused the credentials: HTTP 401")
        assert "check http_user and http_passwd; sent user 'admin'" in message
        with pytest.raises(RetryableError, match="sent no credentials"):
            influx(logger=logger, host="127.0.0.1", port=secured.port, database="secure").send(
                [record({"name": "a", "v": 1})]
            )
        right = influx(logger=logger, **settings)
        assert right.send([record({"name": "a", "v": 1})]) is None
    texts = [message, *(r.getMessage() for r in caplog.records), *(m for _, m in logger.lines)]
    texts += [repr(right.params), repr(wrong.params)]
    token = base64.b64encode(f"admin:{PASSWORD}".encode()).decode()
    for text in texts:
        assert PASSWORD not in text and token not in text, text


# -- v2 against a local receiver (no 2.x server installs here) -----------------------------------------


def test_v2_request_has_org_bucket_precision_token_and_body() -> None:
    with Receiver() as receiver:
        receiver.status = 204
        dest = influx(port=receiver.port, bucket="robots", org="acme co", http_token="tok-" + PASSWORD)
        assert dest.send([record({"name": "cpu", "v": 1}, 5, record_id="id9")]) is None
        (request,) = receiver.requests
    assert request.path == "/api/v2/write?org=acme+co&bucket=robots&precision=ns"
    assert request.header("Authorization") == f"Token tok-{PASSWORD}"
    assert request.header("Content-Encoding") == "gzip"
    assert gzip.decompress(request.body) == b"dc_cpu v=1i 5\n"
    assert request.header("Content-Type") == "text/plain; charset=utf-8"


def test_v2_statuses() -> None:
    answers = {"401": (401, b'{"code":"unauthorized","message":"unauthorized access"}')}

    def respond(request: Request) -> tuple[int, bytes]:
        return answers.get("next", (204, b""))

    with Receiver(respond) as receiver:
        dest = influx(port=receiver.port, bucket="b", http_token="secret-token")
        answers["next"] = (401, b'{"code":"unauthorized","message":"unauthorized access secret-token"}')
        with pytest.raises(RetryableError) as caught:
            dest.send([record({"name": "cpu", "v": 1})])
        assert "check http_token" in str(caught.value) and "secret-token" not in str(caught.value)
        answers["next"] = (404, b'{"code":"not found","message":"bucket \\"b\\" not found"}')
        with pytest.raises(RetryableError, match="bucket 'b' of org 'fluent' not found"):
            dest.send([record({"name": "cpu", "v": 1})])
        answers["next"] = (503, b"busy")
        with pytest.raises(RetryableError, match="HTTP 503"):
            dest.send([record({"name": "cpu", "v": 1})])
        answers["next"] = (422, b'{"code":"unprocessable entity","message":"failure writing points"}')
        outcome = dest.send([record({"name": "cpu", "v": 1}), record({"name": "cpu", "v": 2})])
        assert outcome is not None and sorted(outcome.reject) == [0, 1], "each line refused alone"


# -- TLS: a real influxd over HTTPS; a client certificate against a local receiver (influxd 1.6 asks for none) --


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("tls"))


@pytest.fixture(scope="module")
def https_server(tmp_path_factory: pytest.TempPathFactory, pki: Pki) -> Iterator[InfluxServer]:
    if missing_reason() is not None:
        pytest.skip(str(missing_reason()))
    tls = (pki.server_crt, pki.server_key, pki.ca)
    with InfluxServer(tmp_path_factory.mktemp("influx-tls"), database="dc", tls=tls) as s:
        yield s


@needs_influxd
def test_tls_to_influxd_with_its_ca_file(https_server: InfluxServer) -> None:
    dest = influx(**https_server.settings())
    assert dest.url.startswith("https://127.0.0.1:")
    assert dest.send([record({"name": "tls", "v": n}, STAMP + n) for n in range(3)]) is None
    assert len(rows(https_server, "SELECT * FROM dc_tls")) == 3


@needs_influxd
def test_tls_a_wrong_ca_fails_the_destination_and_keeps_every_record(
    tmp_path: Path, https_server: InfluxServer, pki: Pki
) -> None:
    records = [record({"name": "wrong_ca", "v": n}, STAMP + n) for n in range(4)]
    settings = {**https_server.settings(), "tls_ca_file": str(pki.stranger_ca)}
    dest = InfluxDB(FakeContext(name="tsdb", logger=RecordingLogger()), parse_params(InfluxDBParams, settings, "x"))
    dest.on_configure()
    metrics = through_pipeline(tmp_path, dest, records, lambda m: tls_refused(m) and m["buffered"] == 4)
    delivered = len(rows(https_server, "SELECT * FROM dc_wrong_ca"))
    assert delivered + int(metrics["buffered"]) + int(metrics["dead_lettered"]) == len(records)
    assert delivered == 0 and int(metrics["sent"]) == 0


def test_tls_client_certificate_with_an_encrypted_key(pki: Pki) -> None:
    with Receiver(tls=pki.server_context(client_ca=pki.ca)) as receiver:
        receiver.status = 204
        without = influx(port=receiver.port, tls=True, tls_ca_file=str(pki.ca))
        with pytest.raises(RetryableError):
            without.send([record({"name": "cpu", "v": 1})])
        dest = influx(
            port=receiver.port,
            **pki.client_params(),
        )
        assert dest.send([record({"name": "cpu", "v": 2}, 7, record_id="id2")]) is None
        (request,) = receiver.accepted()
    assert gzip.decompress(request.body) == b"dc_cpu v=2i 7\n"
    assert KEY_PASSWORD not in repr(dest.params)


def test_a_token_over_plain_http_to_another_host_warns_with_the_tls_fix() -> None:
    logger = RecordingLogger()
    influx(logger=logger, host="influx.example.org", bucket="b", http_token="tok")
    (warning,) = [m for level, m in logger.lines if level == "warning"]
    assert "the token sent to influx.example.org without verified TLS" in warning and "set tls: true" in warning


# -- end to end through dc-bringup ------------------------------------------------------------------------


def bringup_params(tmp_path: Path, server: InfluxServer) -> Path:
    # The record ids as fields: the test counts the records stored.
    settings = {"plugin": "dc_destinations/InfluxDB", **server.settings(), "timeout": 2.0, "bookkeeping_fields": True}
    return forwarding_params(tmp_path, "tsdb", settings, measurement="hello", topic="/hello-world")


def publish(run: Bringup, count: int, rate: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [str(BIN / "dc"), "pub", "/hello-world", '{"hello": "world"}', "--count", str(count), "--rate", str(rate)],
        env=run.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def stored_ids(server: InfluxServer) -> set[str]:
    try:
        return {str(r["record_id"]) for r in rows(server, "SELECT record_id FROM dc_hello")}
    except Exception:
        return set()  # the server is down


OUTAGE_S = 30.0


@needs_influxd
@pytest.mark.e2e
def test_e2e_a_30_s_influxdb_outage_loses_no_record(tmp_path: Path) -> None:
    total, rate = 40, 2.0  # 20 s of records: most of them published while the server is down
    server = InfluxServer(tmp_path / "influx", database="dc")
    server.start()
    try:
        with Bringup(bringup_params(tmp_path, server), tmp_path / "home") as run:
            run.wait_ready()
            publisher = publish(run, total, rate)
            run.wait_until(lambda: len(stored_ids(server)) >= 3, 30, "the first points in InfluxDB")
            server.stop()
            down_at = time.monotonic()
            run.wait_stderr(f"cannot write to InfluxDB at http://127.0.0.1:{server.port}", timeout=OUTAGE_S)
            output, _ = publisher.communicate(timeout=2 * OUTAGE_S)  # 20 s of records, and a loaded machine
            assert publisher.returncode == 0, output
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - down_at)))  # the outage lasts 30 s
            server.start()  # the same data folder and port
            run.wait_until(lambda: len(stored_ids(server)) >= total, 30, f"all {total} records after the outage")
        points = rows(server, "SELECT * FROM dc_hello")
    finally:
        server.stop()
    assert len({p["record_id"] for p in points}) == total, "every record stored (a rewrite overwrites, none missing)"
    assert all(p["hello"] == "world" for p in points)
    print(f"\n{len(points)} points for {total} records across a {OUTAGE_S:g} s outage")
