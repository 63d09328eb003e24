"""Slack destination against a local stand-in for Slack's incoming-webhook endpoint.

Slack itself cannot be reached from the tests (no network, no workspace): the receiver here is an
HTTP server on 127.0.0.1 that answers as Slack documents it — ``200 ok``, ``429`` with
``Retry-After``, ``400 invalid_payload``, ``403 invalid_token``, ``404 no_service`` — and keeps each
message with its arrival time. The webhook URLs carry a fake token, checked to appear nowhere.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from types import TracebackType
from typing import Any

import pytest

import dc_destinations.slack as slack_module
from dc_core.destination import OutgoingRecord, RejectedError, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext
from dc_destinations.buffer import FILE_NAME, SqliteBuffer
from dc_destinations.config import parse_destination_server
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from dc_destinations.slack import Slack, SlackParams
from tests.bringup_util import Bringup, dc
from tests.destination_helpers import forwarding_params
from tests.http_receiver import free_port

TOKEN_PATH = "/services/T0SECRET1/B0SECRET2/xoxbFakeTokenVerySecret42"


@dataclass
class Message:
    time: float  # time.monotonic() at arrival
    path: str
    text: str
    content_type: str
    status: int = 0


# What the receiver answers: (status, body, headers).
Answer = tuple[int, bytes, dict[str, str]]


class SlackReceiver:
    """Slack's webhook endpoint as far as the tests need it; ``respond`` sets the answers."""

    def __init__(self, respond: Callable[[Message], Answer] | None = None, *, port: int = 0) -> None:
        self.respond = respond
        self.messages: list[Message] = []
        self.changed = threading.Condition()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                message = Message(
                    time.monotonic(), self.path, json.loads(body)["text"], self.headers.get("Content-Type", "")
                )
                status, answer, headers = receiver.respond(message) if receiver.respond else (200, b"ok", {})
                message.status = status
                with receiver.changed:
                    receiver.messages.append(message)
                    receiver.changed.notify_all()
                self.send_response(status)
                for name, value in {"Content-Type": "text/plain", **headers}.items():
                    self.send_header(name, value)
                self.send_header("Content-Length", str(len(answer)))
                self.end_headers()
                self.wfile.write(answer)

            def log_message(self, format: str, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.server.daemon_threads = True
        self.port = int(self.server.server_address[1])
        self.webhook = f"http://127.0.0.1:{self.port}{TOKEN_PATH}"
        self._thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)

    def __enter__(self) -> SlackReceiver:
        self._thread.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.server.shutdown()
        self.server.server_close()

    def accepted(self) -> list[Message]:
        with self.changed:
            return [m for m in self.messages if m.status == 200]

    def lines(self) -> list[str]:
        return [line for m in self.accepted() for line in m.text.split("\n")]

    def wait_until(self, check: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        with self.changed:
            while not check():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(
                        f"timed out after {timeout} s waiting for {what}; {len(self.messages)} messages"
                    )
                self.changed.wait(min(left, 0.2))


@pytest.fixture
def receiver() -> Iterator[SlackReceiver]:
    with SlackReceiver() as r:
        yield r


def slack_destination(webhook: str, name: str = "slack", context: FakeContext | None = None, **params: Any) -> Slack:
    parsed = parse_params(SlackParams, {"webhook": webhook, **params}, f"destination_server.{name}")
    plugin = Slack(context or FakeContext(name=name), parsed)
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def record(n: int, **data: Any) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(rid, "/dc/measurement/cpu", 1_677_668_906_000_000_000 + n * 10**9, {"record_id": rid, **data})


def cpu(n: int, average: float = 12.345) -> OutgoingRecord:
    return record(n, name="cpu", cpu={"average": average, "cores": [10, 20]}, robot="C3PO", seq=n)


# -- what a message says ---------------------------------------------------------------------------------------


def test_the_template_makes_each_records_line(receiver: SlackReceiver) -> None:
    template = "{robot} {name}: {cpu.average:.1f} % (cores {cpu.cores}, first {cpu.cores.0}) #{seq} {missing}"
    dest = slack_destination(receiver.webhook, template=template, max_records_per_message=3)
    assert dest.send([cpu(n) for n in range(5)]) is None
    first, second = receiver.accepted()
    assert first.path == TOKEN_PATH and first.content_type.startswith("application/json")
    assert first.text.split("\n") == [
        f"C3PO cpu: 12.3 % (cores [10,20], first 10) #{n} {{missing}}" for n in range(3)
    ], "a field the record lacks stays as written"
    assert second.text.split("\n")[-1].endswith("#4 {missing}")


def test_the_default_text_is_a_one_line_summary(receiver: SlackReceiver) -> None:
    rec = record(0, name="uptime", time=92395)
    slack_destination(receiver.webhook).send([rec])
    (message,) = receiver.accepted()
    assert message.text == f"`uptime` at 2023-03-01T11:08:26Z: {rec.to_json()}"


def test_extras_of_the_template(receiver: SlackReceiver) -> None:
    rec = record(0, name="uptime")
    slack_destination(receiver.webhook, template="{topic} {stamp} {record_id} {data}").send([rec])
    assert receiver.accepted()[0].text == f"/dc/measurement/cpu 2023-03-01T11:08:26Z {rec.record_id} {rec.to_json()}"


def test_record_values_cannot_ping_the_channel_or_make_links(receiver: SlackReceiver) -> None:
    dest = slack_destination(receiver.webhook, template="<https://fleet.example.com|fleet>: {note}")
    dest.send([record(0, note="<!channel> R&D <https://evil.example.com|click>")])
    assert receiver.accepted()[0].text == (
        "<https://fleet.example.com|fleet>: &lt;!channel&gt; R&amp;D &lt;https://evil.example.com|click&gt;"
    )


def test_a_template_that_does_not_fit_a_record_falls_back_to_the_summary(receiver: SlackReceiver) -> None:
    context = FakeContext(name="slack")
    dest = slack_destination(receiver.webhook, context=context, template="{name:.1f}")
    assert dest.send([record(0, name="cpu"), record(1, name="cpu")]) is None
    assert all(line.startswith("`cpu` at ") for line in receiver.lines())
    assert len(context.logger.at("warning")) == 1, "warned once, not per record"


def test_a_long_record_is_cut_to_a_readable_line(receiver: SlackReceiver) -> None:
    slack_destination(receiver.webhook).send([record(0, name="blob", pad="x" * 10_000)])
    text = receiver.accepted()[0].text
    assert len(text) == slack_module.LINE_CHARS and text.endswith("…")


# -- rate ------------------------------------------------------------------------------------------------------


def test_at_most_one_message_a_second_within_and_across_batches(receiver: SlackReceiver) -> None:
    dest = slack_destination(receiver.webhook, max_records_per_message=1)
    assert dest.send([cpu(n) for n in range(3)]) is None
    assert dest.send([cpu(3)]) is None
    times = [m.time for m in receiver.accepted()]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert len(gaps) == 3 and min(gaps) >= 0.95, gaps  # 50 ms margin for clock and scheduling
    assert max(gaps) < 1.5, gaps


def test_a_batch_that_does_not_fit_the_send_budget_posts_what_fits_and_returns_the_rest(
    receiver: SlackReceiver, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(slack_module, "SEND_BUDGET_S", 2.5)
    dest = slack_destination(receiver.webhook, rate=2, max_records_per_message=2)
    records = [cpu(n) for n in range(20)]  # 10 messages: 5 s at 2 a second
    started = time.monotonic()
    outcome = dest.send(records)
    assert time.monotonic() - started < 3.5
    assert isinstance(outcome, SendOutcome) and not outcome.reject
    posted = len(receiver.accepted())
    assert 5 <= posted <= 6, posted
    assert sorted(outcome.retry) == list(range(2 * posted, 20))
    assert "held back by rate 2 message(s)/s" in next(iter(outcome.retry.values()))


# -- answers ---------------------------------------------------------------------------------------------------


def pipeline_run(
    tmp_path: Path,
    dest: Slack,
    records: list[OutgoingRecord],
    until: Callable[[DeliveryPipeline], bool],
    *,
    scheduler_cap: float = 0.2,
) -> tuple[str, list[str]]:
    """Deliver ``records`` through the real sender and buffer (small backoff); the status document
    and the dead letters' errors once ``until`` holds."""
    logger: Any = logging.getLogger("test_slack_destination")
    settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=scheduler_cap)
    pipeline = DeliveryPipeline(settings, {"slack": (dest, DestinationDeliveryParams())}, logger)
    pipeline.start()
    try:
        for rec in records:
            pipeline.submit("slack", rec)
        deadline = time.monotonic() + 15
        while not until(pipeline) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert until(pipeline), pipeline.metrics()
        status = json.dumps(pipeline.status_document())
    finally:
        pipeline.stop(0.5)
        dest.on_deactivate()
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        letters = [d.error for d in buffer.list_dead_letters(None)]
    finally:
        buffer.close()
    return status, letters


@pytest.mark.parametrize(("cap", "earliest", "latest"), [(5.0, 1.95, 5.5), (0.5, 0.9, 1.8)])
def test_429_is_retried_after_retry_after_within_scheduler_cap(
    tmp_path: Path, cap: float, earliest: float, latest: float
) -> None:
    """Slack itself cannot be reached here: its documented answers come from SlackReceiver. Its 429
    with Retry-After: 2, then 200: the sender's backoff (0.05 s alone) waits at least
    the 2 s, at most scheduler_cap. Slack's rate keeps the second post a second after the first, so a
    cap below that still gives a gap of about 1 s."""
    answers = iter([(429, b"rate_limited", {"Retry-After": "2"})])
    with SlackReceiver(lambda m: next(answers, (200, b"ok", {}))) as receiver:
        dest = slack_destination(receiver.webhook)
        records = [cpu(n) for n in range(3)]

        def all_sent(p: DeliveryPipeline) -> bool:
            return int(p.metrics()["slack"]["sent"]) == len(records)

        _status, letters = pipeline_run(tmp_path, dest, records, all_sent, scheduler_cap=cap)
    limited, delivered = receiver.messages
    assert limited.status == 429 and delivered.status == 200
    assert earliest <= delivered.time - limited.time <= latest
    posted = [rec.record_id for rec in records if rec.record_id in delivered.text]
    assert len(posted) + len(letters) == len(records), (posted, letters)
    assert len(receiver.accepted()) == 1


def test_429_raises_retryable_with_retry_after_and_does_not_wait_for_it() -> None:
    answers = iter([(429, b"rate_limited", {"Retry-After": "3"}), (429, b"rate_limited", {})])
    with SlackReceiver(lambda m: next(answers, (200, b"ok", {}))) as receiver:
        dest = slack_destination(receiver.webhook, rate=50)
        with pytest.raises(
            RetryableError, match=r"^Slack answered HTTP 429 Too Many Requests: rate_limited; retrying"
        ) as caught:
            dest.send([cpu(0)])
        assert caught.value.retry_after == 3.0
        with pytest.raises(RetryableError) as caught:
            dest.send([cpu(0)])
        assert caught.value.retry_after == slack_module.RETRY_AFTER_DEFAULT_S, "no Retry-After: a second"
        assert dest.send([cpu(0)]) is None
    first, _, third = receiver.messages
    assert third.time - first.time < 1.0, "the waiting is the sender's backoff's, not send's"


@pytest.mark.parametrize("status", [500, 502, 503, 408])
def test_server_errors_are_retryable(status: int) -> None:
    expected = f"Slack answered HTTP {status} .*: slack is having trouble"
    with (
        SlackReceiver(lambda m: (status, b"slack is having trouble", {})) as receiver,
        pytest.raises(RetryableError, match=expected),
    ):
        slack_destination(receiver.webhook).send([cpu(0)])


def test_a_message_slack_refuses_is_rejected_and_the_others_still_go(receiver: SlackReceiver) -> None:
    receiver.respond = lambda m: (400, b"invalid_payload", {}) if "#1" in m.text else (200, b"ok", {})
    dest = slack_destination(receiver.webhook, template="#{seq}", max_records_per_message=1, rate=50)
    outcome = dest.send([cpu(n) for n in range(3)])
    assert isinstance(outcome, SendOutcome) and not outcome.retry
    assert list(outcome.reject) == [1] and "HTTP 400 Bad Request: invalid_payload" in outcome.reject[1]
    assert receiver.lines() == ["#0", "#2"]


@pytest.mark.parametrize(
    ("status", "error"), [(404, b"no_service"), (403, b"invalid_token"), (410, b"channel_is_archived")]
)
def test_a_dead_webhook_dead_letters_the_records_and_never_shows_the_url(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, status: int, error: bytes
) -> None:
    caplog.set_level(logging.DEBUG)
    with SlackReceiver(lambda m: (status, error, {})) as receiver:
        params = parse_params(SlackParams, {"webhook": receiver.webhook}, "destination_server.slack")
        dest = Slack(FakeContext(name="slack"), params)
        dest.on_configure()
        dest.on_activate()
        with pytest.raises(RejectedError) as caught:
            dest.send([cpu(0)])
        status_text, letters = pipeline_run(
            tmp_path, dest, [cpu(1), cpu(2)], lambda p: int(p.metrics()["slack"]["dead_lettered"]) == 2
        )
    assert len(receiver.messages) == 2, "one message for the first send, one for the batch of two; no retry"
    assert re.fullmatch(
        rf"Slack answered HTTP {status} [A-Za-z ]+: {error.decode()} \(http://127\.0\.0\.1:{receiver.port}/\*\*\*\)",
        str(caught.value),
    ), str(caught.value)
    assert len(letters) == 2 and all(error.decode() in e for e in letters)
    texts = [str(caught.value), repr(caught.value), status_text, *letters, repr(params), str(params)]
    texts += [r.getMessage() for r in caplog.records]
    for text in texts:
        assert "SECRET" not in text and "xoxbFake" not in text, text


def test_a_server_quoting_the_url_back_is_masked() -> None:
    with (
        SlackReceiver(lambda m: (500, f"upstream failed for POST {m.path}".encode(), {})) as receiver,
        pytest.raises(RetryableError) as caught,
    ):
        slack_destination(receiver.webhook).send([cpu(0)])
    assert "upstream failed for POST ***" in str(caught.value) and "SECRET" not in str(caught.value)


def test_no_server_is_retryable_without_the_url() -> None:
    port = free_port()
    with pytest.raises(RetryableError) as caught:
        slack_destination(f"http://127.0.0.1:{port}{TOKEN_PATH}").send([cpu(0)])
    assert str(caught.value).startswith(f"cannot POST to the Slack webhook http://127.0.0.1:{port}/***: ")
    assert "refused" in str(caught.value).lower() and "SECRET" not in str(caught.value)


def test_no_answer_within_timeout_is_retryable() -> None:
    release = threading.Event()

    def hang(message: Message) -> Answer:
        release.wait(10)
        return 200, b"ok", {}

    with SlackReceiver(hang) as receiver:
        try:
            with pytest.raises(RetryableError, match=r"no answer within 0.3 s"):
                slack_destination(receiver.webhook, timeout=0.3).send([cpu(0)])
        finally:
            release.set()


def test_a_redirect_is_refused_not_followed(receiver: SlackReceiver) -> None:
    receiver.respond = lambda m: (302, b"", {"Location": "http://127.0.0.1:1/elsewhere"})
    with pytest.raises(RejectedError, match="HTTP 302"):
        slack_destination(receiver.webhook).send([cpu(0)])


# -- configuration ---------------------------------------------------------------------------------------------


def configure(body: dict[str, Any]) -> Slack:
    section = {"destination_plugins": ["slack"], "slack": {"plugin": "dc_destinations/Slack", "inputs": ["/x"], **body}}
    (d,) = parse_destination_server(section).destinations
    plugin: Slack = d.plugin_class(FakeContext(name=d.name), d.plugin_params)
    plugin.on_configure()
    return plugin


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({}, "destination_server.slack.webhook: required parameter missing"),
        ({"webhook": "hooks.slack.com" + TOKEN_PATH}, "destination_server.slack.webhook: expected an https:// URL"),
        ({"webhook": "https://x.example.com/a", "template": "{name"}, "destination_server.slack.template: expected"),
        ({"webhook": "https://x.example.com/a", "rate": 0}, "destination_server.slack.rate: expected a number >= 0.01"),
        ({"webhook": "https://x.example.com/a", "max_records_per_message": 0}, "max_records_per_message: expected"),
    ],
)
def test_configuration_errors_name_the_yaml_path(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(body)
    assert message in str(caught.value)
    assert "SECRET" not in str(caught.value), "the webhook is never quoted"


def test_the_webhook_is_secret() -> None:
    assert {p.name for p in describe_params(SlackParams) if p.secret} == {"webhook"}
    plugin = configure({"plugin": "dc_destinations/FlbSlack", "webhook": "https://hooks.slack.com" + TOKEN_PATH})
    assert "SECRET" not in repr(plugin.params) and plugin.url == "https://hooks.slack.com/***"


# -- end to end through dc-bringup -----------------------------------------------------------------------------

OUTAGE_S = 30.0


def write_params(tmp_path: Path, webhook: str) -> Path:
    template = "{name} {event} {record_id}"
    settings = {"plugin": "dc_destinations/Slack", "webhook": webhook, "template": template, "timeout": 2.0}
    return forwarding_params(tmp_path, "to_slack", settings)


def record_ids(*receivers: SlackReceiver) -> Counter[str]:
    return Counter(line.split()[-1] for r in receivers for line in r.lines())


@pytest.mark.e2e
def test_e2e_records_published_with_dc_pub_arrive_as_messages(tmp_path: Path) -> None:
    with SlackReceiver() as receiver, Bringup(write_params(tmp_path, receiver.webhook), tmp_path / "home") as run:
        run.wait_ready()
        published = dc("pub", "/robot/events", '{"event": "dock"}', "--count", "3", "--rate", "5", env=run.env)
        assert published.returncode == 0, published.stderr
        receiver.wait_until(lambda: len(receiver.lines()) >= 3, 30, "three records")
    assert all(re.fullmatch(r"events dock [0-9a-f-]{36}", line) for line in receiver.lines()), receiver.lines()
    assert len(record_ids(receiver)) == 3
    assert not any("SECRET" in line for line in run.stderr + run.stdout), "the webhook is never logged"


@pytest.mark.e2e
def test_e2e_a_30_s_outage_delays_the_messages_and_loses_nothing(tmp_path: Path) -> None:
    total = 30
    port = free_port()
    webhook = f"http://127.0.0.1:{port}{TOKEN_PATH}"
    with Bringup(write_params(tmp_path, webhook), tmp_path / "home") as run:
        run.wait_ready()
        with SlackReceiver(port=port) as first:
            publisher = dc("pub", "/robot/events", '{"event": "dock"}', "--count", "5", "--rate", "5", env=run.env)
            assert publisher.returncode == 0, publisher.stderr
            first.wait_until(lambda: len(first.lines()) >= 5, 30, "the records before the outage")
        # Slack is unreachable: the records published now wait in the buffer.
        outage_end = time.monotonic() + OUTAGE_S
        during = dc("pub", "/robot/events", '{"event": "dock"}', "--count", str(total - 5), "--rate", "5", env=run.env)
        assert during.returncode == 0, during.stderr
        time.sleep(max(0.0, outage_end - time.monotonic()))  # the outage itself, not a synchronisation
        with SlackReceiver(port=port) as back:
            back.wait_until(lambda: len(record_ids(first, back)) >= total, 30, f"all {total} records")
    assert len(record_ids(first, back)) == total, "every record_id, none missing"
    assert all(b.time - a.time >= 0.95 for a, b in itertools.pairwise(back.accepted()))
    assert not any("SECRET" in line for line in run.stderr + run.stdout)
