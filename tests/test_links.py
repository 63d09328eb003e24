"""Constrained links (dc_destinations.links): only_when, byte caps and priorities, on real loopback links.

The network rules read an injected :class:`~dc_destinations.links.Network` here (a default route that
moves from wwan0 to wlan0): changing the machine's routes needs root. :class:`LinuxNetwork` itself is
read against files laid out as the kernel's. The caps are measured where a link would count them: in
a TCP proxy between the HTTP destination and a real HTTP receiver (tests/throttle_proxy.py).
"""

from __future__ import annotations

import datetime as dt
import itertools
import json
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.cli import _print_delivery
from dc_core.destination import Destination, OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from dc_dashboard.pages import _budget_cells
from dc_destinations.buffer import PendingRecord, SqliteBuffer
from dc_destinations.config import parse_destination_server
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.disk_budget import RecordClass, Step, budget_plan, queue_classes
from dc_destinations.file import File
from dc_destinations.http import Http, HttpParams
from dc_destinations.links import FILES, RECORDS, LinuxNetwork, OnlyWhenParams, SendRules, TokenBucket
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.destination_helpers import make
from tests.http_receiver import Receiver
from tests.throttle_proxy import ThrottleProxy

LOG = logging.getLogger("tests.test_links")


class FakeNetwork:
    """The default route and interfaces a test sets."""

    def __init__(self, route: str | None, interfaces: dict[str, bool]) -> None:
        self.route = route
        self.interfaces = interfaces

    def default_route(self) -> str | None:
        return self.route

    def interface_up(self, name: str) -> bool | None:
        return self.interfaces.get(name)


def rules(network: FakeNetwork, now: dt.datetime | None = None, **only_when: Any) -> SendRules:
    params = parse_params(OnlyWhenParams, only_when, "destination_server.d.only_when")
    # A clock a second further at each look: every held() reads the network again.
    return SendRules(params, network, now=(lambda: now) if now else None, clock=itertools.count().__next__)


def test_only_when_says_why_it_holds() -> None:
    net = FakeNetwork("wwan0", {"wwan0": True, "wlan0": False})
    metered = rules(net, default_route_not_via=["wwan0"])
    assert metered.held() == "held: wwan0 is the default route"
    wifi = rules(net, default_route_via=["wlan0"])
    assert wifi.held() == "held: wwan0 is the default route, not wlan0"
    net.route = "wlan0"
    assert metered.held() == wifi.held() == ""
    net.route = None
    assert wifi.held() == "held: there is no default route"
    assert metered.held() == ""  # no route through the metered modem: nothing to hold for

    up = rules(net, interfaces_up=["wlan0", "eth9"])
    assert up.held() == "held: interface wlan0 is down"
    net.interfaces["wlan0"] = True
    assert up.held() == "held: interface eth9 does not exist"
    assert up.missing_interfaces() == ["eth9"]
    net.interfaces["eth9"] = True  # it appears: the rule holds no more
    assert up.held() == ""

    docked = rules(net, conditions=["docked"])
    assert docked.held() == "held: condition docked not heard yet"
    assert docked.condition_changed("docked", False) and not docked.condition_changed("other", True)
    assert docked.held() == "held: condition docked is false"
    docked.condition_changed("docked", True)
    assert docked.held() == ""


@pytest.mark.parametrize(
    ("window", "hour", "inside"),
    [("22:00-06:00", 23, True), ("22:00-06:00", 3, True), ("22:00-06:00", 12, False), ("09:00-17:30", 17, True)],
)
def test_only_when_daily_window_wraps_past_midnight(window: str, hour: int, inside: bool) -> None:
    now = dt.datetime(2026, 11, 26, hour, 15, tzinfo=dt.UTC)
    rule = rules(FakeNetwork(None, {}), now, window=window, window_utc=True)
    assert rule.held() == ("" if inside else f"held: outside {window} (UTC)")


def test_linux_network_reads_the_kernels_tables(tmp_path: Path) -> None:
    route = tmp_path / "route"
    route.write_text(
        "Iface\tDestination\tGateway \tFlags\tRefCnt\tUse\tMetric\tMask\t\tMTU\tWindow\tIRTT\n"
        "wlan0\t0000A8C0\t00000000\t0001\t0\t0\t600\t00FFFFFF\t0\t0\t0\n"
        "wwan0\t00000000\t0100A8C0\t0003\t0\t0\t700\t00000000\t0\t0\t0\n"
        "wlan0\t00000000\t0101A8C0\t0003\t0\t0\t600\t00000000\t0\t0\t0\n"
    )
    sys_net = tmp_path / "net"
    (sys_net / "wlan0").mkdir(parents=True)
    (sys_net / "wlan0" / "flags").write_text("0x1003\n")
    (sys_net / "wwan0").mkdir()
    (sys_net / "wwan0" / "flags").write_text("0x1002\n")
    network = LinuxNetwork(route, sys_net)
    assert network.default_route() == "wlan0"  # the lower metric wins
    assert network.interface_up("wlan0") is True
    assert network.interface_up("wwan0") is False
    assert network.interface_up("eth9") is None
    assert network.interface_up("../etc") is None
    assert LinuxNetwork().interface_up("lo") is True  # this machine's own


def server_section(flb: dict[str, Any] | None = None, **dest: Any) -> dict[str, Any]:
    return {
        "destination_plugins": ["d"],
        "flb": flb or {},
        "d": {"plugin": "dc_destinations/Null", "inputs": ["/dc/measurement/x"], **dest},
    }


@pytest.mark.parametrize(
    ("section", "path", "says"),
    [
        (server_section(only_when={"window": "25:00-06:00"}), "destination_server.d.only_when.window", "HH:MM"),
        (server_section(only_when={"window": "06:00-06:00"}), "destination_server.d.only_when.window", "empty"),
        (server_section(max_bytes_per_s="0"), "destination_server.d.max_bytes_per_s", "never send"),
        (server_section({"links": {"lte": "0"}}, link="lte"), "destination_server.flb.links.lte", "never send"),
        (server_section({"links": {"lte": "125k"}}, link="wifi"), "destination_server.d.link", 'no link "wifi"'),
        (server_section(only_when={"interface_up": ["wlan0"]}), "destination_server.d.only_when.interface_up", ""),
        (
            server_section(retention_priorities={"camera": 1}),
            "destination_server.d.retention_priorities.camera",
            "no input topic nor measurement",
        ),
        (
            server_section(retention_priorities={"/dc/measurement/y": 1}),
            "destination_server.d.retention_priorities./dc/measurement/y",
            "no input topic nor measurement",
        ),
        (server_section(retention_priorities={"x": "high"}), "destination_server.d.retention_priorities.x", "integer"),
    ],
)
def test_bad_rules_and_caps_are_configure_errors(section: dict[str, Any], path: str, says: str) -> None:
    with pytest.raises(ConfigError) as raised:
        parse_destination_server(section)
    assert raised.value.path == path and says in raised.value.message


def test_retention_priorities_name_the_destinations_inputs_by_topic_or_measurement() -> None:
    config = parse_destination_server(server_section(retention_priorities={"x": 3, "dc/measurement/x": 5}))
    (destination,) = config.destinations
    assert destination.delivery.retention_priorities == {"x": 3, "/dc/measurement/x": 5}


def test_unknown_interface_is_a_warning_and_holds(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    params = DestinationDeliveryParams(only_when=OnlyWhenParams(interfaces_up=["wlan7"]))
    sink = Collecting()
    with caplog.at_level(logging.WARNING):
        pipeline = DeliveryPipeline(fast(tmp_path), {"d": (sink, params)}, LOG, network=FakeNetwork(None, {}))
    assert "only_when names wlan7, which this machine does not have" in caplog.text
    pipeline.start()
    try:
        pipeline.submit("d", record(1))
        poll(lambda: pipeline.metrics()["d"]["held"] == "held: interface wlan7 does not exist", 3, "held")
        assert sink.received == []
        assert 'dc_delivery_held{destination="d"} 1' in pipeline.prometheus()
        _print_delivery(pipeline.status_document(), wide=False)  # what `dc status` prints of it
    finally:
        pipeline.stop(0.2)
    shown = capsys.readouterr().out
    assert "destination d held: interface wlan7 does not exist" in shown
    (row,) = [line for line in shown.splitlines() if line.split()[:1] == ["d"]]
    assert row.split()[1] == "held"  # its health column


def test_token_bucket_keeps_its_rate_and_serves_records_before_files() -> None:
    # The burst is served with no time passing (a clock that stands still), and then nothing more.
    still = TokenBucket(20_000, 4_000, clock=lambda: 0.0)
    assert still.take(4_000, threading.Event())
    given_up = threading.Event()
    threading.Timer(0.2, given_up.set).start()
    assert not still.take(1, given_up)

    bucket = TokenBucket(20_000, 4_000)
    stop = threading.Event()
    order: list[str] = []
    start = time.monotonic()
    assert bucket.take(4_000, stop)  # the burst

    # Files ask first for less; records asking while they wait still go first.
    def upload() -> None:
        if bucket.take(2_000, stop, kind=FILES):
            order.append("files")

    files = threading.Thread(target=upload)
    files.start()
    time.sleep(0.02)  # the files' waiter is queued (ordering only: no result depends on its length)
    assert bucket.take(4_000, stop, kind=RECORDS)
    order.append("records")
    files.join(2)
    assert order == ["records", "files"]
    # 10,000 bytes at 20,000/s, 4,000 of them saved up: 0.3 s at least (a loaded machine only adds).
    assert time.monotonic() - start >= 0.28
    stop.set()
    assert not bucket.take(10_000, stop)


# -- through the real sender, a proxy and a real receiver ---------------------------------------


class Collecting(Destination[None]):
    def __init__(self, name: str = "d") -> None:
        super().__init__(FakeContext(name=name), None)
        self.received: list[OutgoingRecord] = []

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        self.received.extend(batch)
        return None


class FileUploader(Destination[None]):
    """Sends a large "file" of each record in 8 KiB pieces through the same link, as MinIO's parts."""

    def __init__(self, size: int) -> None:
        super().__init__(FakeContext(name="files"), None)
        self.size = size
        self.sent = 0

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        for _ in batch:
            for _ in range(self.size // 8192):
                if not self.pace(8192):
                    raise RetryableError("stopping")
                self.sent += 8192
        return None


def record(n: int, pad: int = 0) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(rid, "/dc/measurement/x", time.time_ns(), {"n": n, "pad": "x" * pad, "record_id": rid})


def fast(tmp_path: Path, **flb: Any) -> DeliveryParams:
    return DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=0.2, **flb)


def http_to(port: int) -> Http:
    plugin = Http(FakeContext(name="web"), parse_params(HttpParams, {"port": port}, "destination_server.web"))
    plugin.on_configure()
    return plugin


def poll(check: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    with Receiver() as r:
        yield r


@pytest.fixture
def link(receiver: Receiver) -> Iterator[ThrottleProxy]:
    with receiver.changed:
        receiver.requests.clear()
    with ThrottleProxy(("127.0.0.1", receiver.port), latency=0.005) as proxy:
        yield proxy


def test_cap_holds_on_the_wire(tmp_path: Path, receiver: Receiver, link: ThrottleProxy) -> None:
    """150 kB of records through a 40 kB/s cap with a 20 kB burst: on the wire (HTTP headers
    included) no 1 s window carries more than the cap plus the burst, and the link is used at
    >= 90 % of the cap."""
    rate, burst = 40_000, 20_000
    web = http_to(link.port)
    pipeline = DeliveryPipeline(
        fast(tmp_path, burst_s=burst / rate),
        {"web": (web, DestinationDeliveryParams(max_bytes_per_s=str(rate), batch_size=20))},
        LOG,
    )
    web.on_activate()
    pipeline.start()
    try:
        for n in range(300):
            pipeline.submit("web", record(n, pad=440))
        receiver.wait_until(lambda: len(receiver.records()) >= 300, 10, "the records")
    finally:
        pipeline.stop(0.2)
        web.on_deactivate()
    times = [t for t, _ in link.upstream]
    start, end = times[0], times[-1]
    # The cap counts the records' bytes, not HTTP's headers (~250 B a request of ~9 kB of records,
    # docs/constrained_links.md): the wire may carry that much more. A CI run measured 61,852 B in the
    # first second for 60,000 B of cap and burst.
    headers = 1.05
    t = start
    while t < end:
        window = link.sent_between(t, t + 1.0)
        assert window <= (rate + burst) * headers, (t - start, window)
        t += 0.25
    total = link.sent_between(start, end + 1)
    assert total >= 0.9 * rate * (end - start), (total, end - start)


def test_records_pass_the_files_on_a_shared_link(tmp_path: Path, receiver: Receiver, link: ThrottleProxy) -> None:
    """Records (HTTP, through the proxy) and a file uploader share a 40 kB/s link: the files use it
    whole, yet no record waits behind them, and the files keep to the link's pace."""
    rate = 40_000
    web = http_to(link.port)
    files = FileUploader(size=64 * 1024)
    pipeline = DeliveryPipeline(
        fast(tmp_path, links={"lte": str(rate)}, burst_s=0.25),
        {
            "web": (web, DestinationDeliveryParams(link="lte", batch_size=20)),
            "files": (files, DestinationDeliveryParams(link="lte", batch_size=1)),
        },
        LOG,
    )
    web.on_activate()
    pipeline.start()
    sent: dict[int, float] = {}
    try:
        for n in range(2):  # 2 files of 64 KiB: over 3 s of the link
            pipeline.submit("files", record(n))
        poll(lambda: files.sent > 0, 2, "the files under way")
        start = time.monotonic()
        files_start = start
        for n in range(20):  # meanwhile a record each 0.1 s
            sent[n] = time.monotonic()
            pipeline.submit("web", record(n, pad=400))
            time.sleep(0.1)
        receiver.wait_until(lambda: len(receiver.records()) >= 20, 5, "the records")
        poll(lambda: pipeline.metrics()["files"]["sent"] == 2, 10, "the files")
        end = time.monotonic()
    finally:
        pipeline.stop(0.2)
        web.on_deactivate()
    latencies = sorted(r.time - sent[rec["n"]] for r in receiver.accepted() for rec in _records_of(r))
    # A record waits for the file piece under way (8 KiB: 0.2 s of the link), never for the files
    # (over 3 s): 2 s leaves room for a loaded machine. How much of the link is used is measured in
    # benchmarks/links.py, not asserted here (a loaded CI machine used 87 % of it).
    assert latencies[-1] < 2.0, latencies[-5:]
    assert files.sent == 2 * 64 * 1024
    assert end - files_start >= (files.sent - 0.25 * rate) / rate * 0.9  # the files went at the link's pace


def _records_of(request: Any) -> list[dict[str, Any]]:
    import json

    return list(json.loads(request.body))


def test_outage_and_only_when_lose_nothing(tmp_path: Path, receiver: Receiver, link: ThrottleProxy) -> None:
    """On a 1 Mbit/s link with 300 ms latency, the link goes away, then the default route moves to
    the metered modem: records wait, the destination says why, and every record arrives once it is
    allowed again (sent = delivered)."""
    link.rate, link.latency = 125_000, 0.3  # 1 Mbit/s and 300 ms each way, as LTE
    network = FakeNetwork("wlan0", {"wlan0": True, "wwan0": True})
    web = http_to(link.port)
    params = DestinationDeliveryParams(only_when=OnlyWhenParams(default_route_not_via=["wwan0"]), batch_size=50)
    pipeline = DeliveryPipeline(fast(tmp_path), {"web": (web, params)}, LOG, network=network)
    web.on_activate()
    pipeline.start()
    try:
        ids = []
        link.cut()
        for n in range(100):
            rec = record(n)
            ids.append(rec.record_id)
            pipeline.submit("web", rec)
        poll(lambda: pipeline.metrics()["web"]["retried"] > 0, 5, "a failed attempt")
        link.restore()
        poll(lambda: pipeline.metrics()["web"]["sent"] == 100, 10, "delivery after the outage")

        network.route = "wwan0"
        poll(lambda: pipeline.metrics()["web"]["held"] == "held: wwan0 is the default route", 2, "held")
        assert pipeline.health_document()["destinations"]["web"]["held"] == "held: wwan0 is the default route"
        for n in range(100, 150):
            rec = record(n)
            ids.append(rec.record_id)
            pipeline.submit("web", rec)
        assert pipeline.flush_intake(5)
        time.sleep(0.5)  # held for a while: nothing may go
        assert pipeline.metrics()["web"]["sent"] == 100 and pipeline.metrics()["web"]["buffered"] == 50

        network.route = "wlan0"
        poll(lambda: pipeline.metrics()["web"]["held"] == "", 1, "sending again within a second")
        poll(lambda: pipeline.metrics()["web"]["sent"] == 150, 5, "delivery once allowed")
        metrics = pipeline.metrics()["web"]
    finally:
        pipeline.stop(0.2)
        web.on_deactivate()
    delivered = {r["record_id"] for r in receiver.records()}
    assert metrics["held"] == ""
    assert delivered == set(ids)
    assert metrics["sent"] + metrics["dropped"] + metrics["dead_lettered"] + metrics["buffered"] == len(ids)


def test_a_condition_releases_held_records_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A held sender looks again every HOLD_POLL_S (0.25 s): a minute here, so that only the wake-up
    # of the condition's change can deliver within the poll below (no timing to assert).
    monkeypatch.setattr("dc_destinations.sender.HOLD_POLL_S", 60.0)
    sink = Collecting()
    params = DestinationDeliveryParams(only_when=OnlyWhenParams(conditions=["docked"]))
    pipeline = DeliveryPipeline(fast(tmp_path), {"d": (sink, params)}, LOG)
    pipeline.start()
    try:
        assert pipeline.conditions() == ["docked"]
        pipeline.submit("d", record(1))
        poll(lambda: pipeline.metrics()["d"]["held"] == "held: condition docked not heard yet", 2, "held")
        pipeline.set_condition("docked", True)
        poll(lambda: len(sink.received) == 1, 30, "delivery woken by the change, not by the next look")
    finally:
        pipeline.stop(0.2)


# -- the disk budget ------------------------------------------------------------------------------


def test_eviction_plan_gives_up_the_lowest_retention_priority_first() -> None:
    classes = queue_classes({"images": 300, "health": 500, "maps": 100}, {"images": 0, "maps": 0, "health": 5})
    low = (("images", None), ("maps", None))
    assert budget_plan(classes, [], 0) == []
    # The oldest of priority 0 across both queues (the buffer picks them), then priority 5.
    assert budget_plan(classes, [], 200) == [Step("records", "0", 200, low)]
    assert budget_plan(classes, [], 600) == [
        Step("records", "0", 400, low),
        Step("records", "5", 200, (("health", None),)),
    ]
    # A destination whose records have priorities per input topic: a class per priority.
    by_topic = [
        RecordClass("robot", ("/dc/measurement/camera",), 0, 300),
        RecordClass("robot", ("/dc/measurement/health", "/dc/group/robot"), 10, 500),
        RecordClass("maps", None, 5, 100),
    ]
    assert budget_plan(by_topic, [], 350) == [
        Step("records", "0", 300, (("robot", ("/dc/measurement/camera",)),)),
        Step("records", "5", 50, (("maps", None),)),
    ]


def test_disk_budget_evicts_by_retention_and_counts_it(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Two held destinations fill a 1 MB budget 1.2 times over: the low retention priority gives up
    its oldest records, the high keeps all; every record is delivered, buffered or evicted."""
    held = OnlyWhenParams(conditions=["docked"])
    images, health = Collecting("images"), Collecting("health")
    pipeline = DeliveryPipeline(
        fast(tmp_path, disk_budget_mb=1.0),
        {
            "images": (images, DestinationDeliveryParams(only_when=held, retention_priority=0)),
            "health": (health, DestinationDeliveryParams(only_when=held, retention_priority=5)),
        },
        LOG,
    )
    dropped: list[tuple[str, list[str], str]] = []
    pipeline.add_drop_listener(lambda *drop: dropped.append(drop))
    pipeline.start()
    try:
        with caplog.at_level(logging.WARNING):
            for n in range(60):  # 60 records of ~10 kB each
                pipeline.submit("images", record(n, pad=10_000))
                pipeline.submit("health", record(n, pad=10_000))
            assert pipeline.flush_intake(5)
            poll(lambda: within(pipeline.metrics(), 1024 * 1024), 3, "the buffer within its budget")
        metrics = pipeline.metrics()
        assert metrics["health"]["evicted"] == 0 and metrics["health"]["buffered"] == 60
        assert metrics["images"]["evicted"] > 0
        assert "records evicted unsent to keep DC within its disk budget" in caplog.text
        pipeline.set_condition("docked", True)
        poll(lambda: all(m["received"] == m["sent"] + m["evicted"] for m in pipeline.metrics().values()), 3, "sent")
        # The oldest went: what arrived of images is its newest records, in order.
        kept = [r.data["n"] for r in images.received]
        assert kept == list(range(60 - len(kept), 60))
        # Whoever listens (dc ingest) is told which records were evicted, and why.
        assert {(name, why) for name, _, why in dropped} == {("images", "disk_budget")}
        told = [rid for _, ids, _ in dropped for rid in ids]
        assert sorted(told) == sorted(set(told)) and len(told) == metrics["images"]["evicted"]
        assert not set(told) & {r.record_id for r in images.received}
        after = pipeline.metrics()
    finally:
        pipeline.stop(0.2)
    for name in ("images", "health"):
        m = after[name]
        assert m["received"] == m["sent"] + m["evicted"] + m["dropped"] + m["buffered"] == 60
    assert 'dc_delivery_evicted_total{destination="images"}' in pipeline.prometheus()


def within(metrics: dict[str, Any], budget: int) -> bool:
    return sum(m["buffered_bytes"] or 0 for m in metrics.values()) <= budget


CAMERA, HEALTH = "/dc/measurement/camera", "/dc/measurement/health"


def measured(topic: str, n: int, pad: int = 10_000) -> OutgoingRecord:
    rid = new_record_id()
    name = topic.rsplit("/", 1)[-1]
    return OutgoingRecord(rid, topic, time.time_ns(), {"m": name, "n": n, "pad": "x" * pad, "record_id": rid})


def test_disk_budget_evicts_the_records_of_one_destination_by_their_measurements_priority(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Camera and health records through one File destination held off the dock, over a 1 MB budget:
    the camera's records (retention priority 0) go, oldest first, until none is left, only then the
    oldest health records (10); each counted per measurement; at the dock every other record reaches
    the file: delivered + evicted = sent, per measurement."""
    robot = make(File, "robot", path=str(tmp_path / "out"))
    robot.on_activate()
    params = DestinationDeliveryParams(
        only_when=OnlyWhenParams(conditions=["docked"]), retention_priority=0, retention_priorities={"health": 10}
    )
    pipeline = DeliveryPipeline(fast(tmp_path / "buffer", disk_budget_mb=1.0), {"robot": (robot, params)}, LOG)
    budget = 1024 * 1024
    pipeline.start()
    try:
        for n in range(55):  # ~10 kB each: 1.1 MB of both, interleaved, a little over the budget
            pipeline.submit("robot", measured(CAMERA, n))
            pipeline.submit("robot", measured(HEALTH, n))
        assert pipeline.flush_intake(10)
        poll(lambda: within(pipeline.metrics(), budget), 30, "the buffer within its budget")
        first = pipeline.metrics()["robot"]
        for n in range(55, 105):  # health only, 0.5 MB: the camera's last records go, then the oldest health
            pipeline.submit("robot", measured(HEALTH, n))
        assert pipeline.flush_intake(10)
        poll(lambda: within(pipeline.metrics(), budget), 30, "the buffer within its budget again")
        second = pipeline.metrics()["robot"]
        _print_delivery(pipeline.status_document(), wide=False)
        pipeline.set_condition("docked", True)
        poll(lambda: pipeline.metrics()["robot"]["buffered"] == 0, 30, "the rest delivered")
        last = pipeline.metrics()["robot"]
    finally:
        pipeline.stop(0.2)
    # Over the budget with camera records left, only those went.
    assert 0 < first["evicted"] < 55 and first["evicted_by_measurement"] == {"camera": first["evicted"]}
    # The second time every camera record went before the first health record.
    evicted = second["evicted_by_measurement"]
    assert evicted["camera"] == 55 and evicted.get("health", 0) > 0
    assert second["evicted"] == sum(evicted.values())
    said = f"{second['evicted']} records and 0 saved files evicted unsent by the disk budget (records of camera 55, "
    assert f"destination robot: {said}health {evicted['health']})" in capsys.readouterr().out
    assert f"(camera 55, health {evicted['health']})</td>" in _budget_cells(second)
    lines = [json.loads(line) for line in (tmp_path / "out" / "robot").read_text().splitlines()]
    assert not [r for r in lines if r["m"] == "camera"]
    kept = [r["n"] for r in lines if r["m"] == "health"]
    assert kept == list(range(105 - len(kept), 105)), "the oldest health records went, the newest stayed"
    assert len(kept) + last["evicted_by_measurement"]["health"] == 105
    assert last["received"] == last["sent"] + last["evicted"] == 160 and last["sent"] == len(lines)
    assert 'dc_delivery_evicted_by_measurement_total{destination="robot",measurement="camera"} 55' in (
        pipeline.prometheus()
    )


def test_size_limit_drops_are_counted_per_measurement(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A File destination held off the dock with a 100 kB size limit (drop_oldest): 20 camera records,
    then 15 health records, of 10 kB. The oldest go: every camera record, then the oldest health
    records; counted per measurement in the metrics, the Prometheus text, `dc status` and the Health
    page. At the dock the rest reach the file: delivered + dropped = sent, per measurement."""
    robot = make(File, "robot", path=str(tmp_path / "out"))
    robot.on_activate()
    params = DestinationDeliveryParams(only_when=OnlyWhenParams(conditions=["docked"]), storage_total_limit_size="100k")
    pipeline = DeliveryPipeline(fast(tmp_path / "buffer"), {"robot": (robot, params)}, LOG)
    pipeline.start()
    try:
        for n in range(20):
            pipeline.submit("robot", measured(CAMERA, n))
        for n in range(15):
            pipeline.submit("robot", measured(HEALTH, n))
        assert pipeline.flush_intake(10)
        held = pipeline.metrics()["robot"]
        _print_delivery(pipeline.status_document(), wide=False)
        prometheus = pipeline.prometheus()
        pipeline.set_condition("docked", True)
        poll(lambda: pipeline.metrics()["robot"]["buffered"] == 0, 30, "the rest delivered")
        last = pipeline.metrics()["robot"]
    finally:
        pipeline.stop(0.2)
    lines = [json.loads(line) for line in (tmp_path / "out" / "robot").read_text().splitlines()]
    delivered = {name: [r["n"] for r in lines if r["m"] == name] for name in ("camera", "health")}
    dropped = held["dropped_by_measurement"]
    assert dropped["camera"] == 20 and delivered["camera"] == [], "every camera record went before a health record"
    assert 0 < dropped["health"] < 15 and delivered["health"] == list(range(dropped["health"], 15))
    assert held["dropped"] == sum(dropped.values()) and last["dropped_by_measurement"] == dropped
    assert last["received"] == last["sent"] + last["dropped"] == 35 and last["sent"] == len(lines)
    said = f"destination robot: {held['dropped']} records dropped by its size limit (storage_total_limit_size) or "
    assert f"{said}a full intake (records of camera 20, health {dropped['health']})" in capsys.readouterr().out
    assert f"<td class=num>{held['dropped']} (camera 20, health {dropped['health']})</td>" in _budget_cells(held)
    assert 'dc_delivery_dropped_by_measurement_total{destination="robot",measurement="camera"} 20' in prometheus


def test_an_earlier_buffer_is_delivered_under_priorities_per_topic(tmp_path: Path) -> None:
    """Records an earlier DC left in the buffer (its queues have no index by topic) are delivered by
    a destination that now has retention_priorities."""
    earlier = SqliteBuffer(tmp_path / "delivery.sqlite3")
    earlier.append({"d": [PendingRecord(f"id-{n}", CAMERA if n % 2 else HEALTH, n, f'{{"n":{n}}}') for n in range(20)]})
    earlier.close()
    sink = Collecting()
    params = DestinationDeliveryParams(retention_priorities={"camera": -1})
    pipeline = DeliveryPipeline(fast(tmp_path, disk_budget="50M"), {"d": (sink, params)}, LOG)
    pipeline.start()
    try:
        poll(lambda: len(sink.received) == 20, 30, "the earlier records delivered")
    finally:
        pipeline.stop(0.2)
    assert [r.record_id for r in sink.received] == [f"id-{n}" for n in range(20)]
    assert {r.topic for r in sink.received} == {CAMERA, HEALTH}


def test_a_budget_below_one_batch_is_refused() -> None:
    with pytest.raises(ConfigError) as raised:
        parse_destination_server(server_section({"disk_budget_mb": 0.5}))
    assert raised.value.path == "destination_server.flb.disk_budget_mb" and "smaller than" in raised.value.message
