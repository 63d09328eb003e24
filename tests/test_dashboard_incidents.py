"""`dc dashboard`'s Incidents page: the Recorder's records in a real PostgreSQL, their MCAP files in a real S3
(SeaweedFS), listed with the filters and downloaded through the dashboard."""

from __future__ import annotations

import datetime as dt
import http.client
import json
import tempfile
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers import postgres, seaweedfs
from dc_dashboard.server import Dashboard, make_server
from dc_dashboard.settings import DashboardSettings, PostgresSettings, S3Settings
from tests.destination_helpers import running_postgres

T0 = dt.datetime(2026, 3, 1, 12, 0, 0)
BIG = 16 * 1024 * 1024  # more than a socket's buffers hold: the dashboard is still writing when the client goes


def _scan(messages: int, bound: int = 0, transport: int = 0) -> dict[str, Any]:
    return {
        "topic": "/scan",
        "type": "sensor_msgs/msg/LaserScan",
        "messages": messages,
        "bytes": messages * 5800,
        "lost_to_memory_bound": bound,
        "lost_in_transport": transport,
        "absent": False,
    }


def _incident(
    robot: str, run: str, at: dt.datetime, reasons: list[str], key: str, size: int, more: tuple[Any, ...] = ()
) -> dict[str, Any]:
    """A record as dc_measurements/Recorder publishes it (dc_measurements/recorder/schema.json)."""
    t = at.replace(tzinfo=dt.UTC).timestamp()
    return {
        "name": "incidents",
        "robot_name": robot,
        "run_id": run,
        "start": t - 10.0,
        "end": t + 5.0,
        "triggers": [{"time": t + i, "reason": r} for i, r in enumerate(reasons)],
        "topics": [
            {
                "topic": "/odom",
                "type": "nav_msgs/msg/Odometry",
                "messages": 750,
                "bytes": 543750,
                "lost_to_memory_bound": 0,
                "absent": False,
            },
            {
                "topic": "/camera/compressed",
                "type": "",
                "messages": 0,
                "bytes": 0,
                "lost_to_memory_bound": 0,
                "absent": True,
            },
            *more,
        ],
        "messages": 750,
        "size": size,
        "cut_by_memory_bound": False,
        "local_paths": {"mcap": f"/home/robot/{key}"},
        "remote_paths": {"minio": {"mcap": key}},
        "date": 0,
    }


@dataclass
class Servers:
    postgres: PostgresSettings
    s3: S3Settings
    mcap: bytes  # the real incident file in the bucket


@pytest.fixture(scope="module")
def servers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Servers]:
    import psycopg

    from dc_measurements.recorder.definitions import Definitions
    from dc_measurements.recorder.mcap_file import Channel, write_mcap

    for missing in (postgres.missing_reason(), seaweedfs.missing_reason()):
        if missing is not None:
            pytest.fail(missing)  # make test-deps installs them: a skip would hide a missing dependency
    tmp = tmp_path_factory.mktemp("incidents")
    mcap_path = tmp / "incident.mcap"
    write_mcap(str(mcap_path), [Channel("/odom", "nav_msgs/msg/Odometry")], [(1, 1, 0, b"\x00\x01\x00\x00odom")],
               "zstd", Definitions().get)  # fmt: skip
    mcap = mcap_path.read_bytes()
    rows = [
        # /scan recorded but silent in this window: no message of it in the file
        _incident("C3PO", "1", T0, ["conditions"], "C3PO/incidents/a.mcap", len(mcap), (_scan(0),)),
        _incident("C3PO", "2", T0 + dt.timedelta(hours=1), ["service", "bumper hit"], "C3PO/incidents/b.mcap", 9),
        _incident(
            "R2D2",
            "1",
            T0 + dt.timedelta(minutes=30),
            ["operator: Bumper"],
            "R2D2/incidents/c.mcap",
            9,
            (_scan(150, 2, 3),),
        ),
        {"name": "speed", "computed": 1.0, "robot_name": "C3PO", "run_id": "1", "date": 0},
    ]
    with running_postgres("dc-pg-incidents-") as pg, seaweedfs.SeaweedS3Server(Path(tempfile.mkdtemp()) / "s3") as s3:
        settings = PostgresSettings(port=pg.port, user=pg.user, password=pg.password, database=pg.database)
        with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
            connection.execute("CREATE TABLE dc (tag varchar, time timestamp, data jsonb, record_id text)")
            with connection.cursor() as cursor:
                cursor.executemany(
                    "INSERT INTO dc VALUES ('flb_pgsql', %s, %s::jsonb, %s)",
                    [
                        (dt.datetime.fromtimestamp(r.get("start", 0) + 10, dt.UTC).replace(tzinfo=None), json.dumps(r),
                         str(i))
                        for i, r in enumerate(rows)
                    ],
                )  # fmt: skip
        client = s3.client()
        client.put_object(Bucket=s3.bucket, Key="C3PO/incidents/a.mcap", Body=mcap)
        client.put_object(Bucket=s3.bucket, Key="C3PO/incidents/b.mcap", Body=b"not mcap!")
        client.put_object(Bucket=s3.bucket, Key="C3PO/incidents/big.mcap", Body=mcap[:8] + bytes(BIG))
        s3_settings = S3Settings(
            endpoint=s3.endpoint,
            access_key_id=s3.access_key,
            secret_access_key=str(s3.settings()["aws_secret_access_key"]),
            bucket=s3.bucket,
        )
        yield Servers(settings, s3_settings, mcap)


def _rows(html: str) -> list[str]:
    return html.split("<tr class=incident>")[1:]


def test_the_incidents_page_lists_reasons_topics_and_sizes_with_the_robot_time_and_reason_filters(
    servers: Servers,
) -> None:
    dashboard = Dashboard(DashboardSettings(servers.postgres, servers.s3))
    status, html = dashboard.render("/incidents", "")
    assert status == 200 and len(_rows(html)) == 3
    assert '<a href="/incidents" class="active">Incidents</a>' in html  # in the navigation
    newest = _rows(html)[0]  # newest first
    assert "service, bumper hit" in newest and "<td>C3PO</td><td>2</td><td>incidents</td>" in newest
    assert "/odom: 750 messages, 531.0 KiB" in newest and "/camera/compressed: absent" in newest
    assert "(15.0 s)" in newest and "<td class=num>9 B</td>" in newest
    # Robot
    status, html = dashboard.render("/incidents", "robot=R2D2")
    assert status == 200 and [("R2D2" in r) for r in _rows(html)] == [True]
    # Time range (UTC)
    status, html = dashboard.render("/incidents", "start=2026-03-01T12:20&end=2026-03-01T12:40")
    assert status == 200 and len(_rows(html)) == 1 and "operator: Bumper" in html
    # Reason: any trigger's, any case, a % taken literally
    status, html = dashboard.render("/incidents", "reason=bumper")
    assert status == 200 and len(_rows(html)) == 2
    assert 'value="bumper"' in html
    status, html = dashboard.render("/incidents", "reason=%25")
    assert status == 200 and not _rows(html) and "no incident with a reason holding %" in html


def test_the_incidents_page_filters_by_a_topic_with_messages_in_the_file(servers: Servers) -> None:
    dashboard = Dashboard(DashboardSettings(servers.postgres, servers.s3))
    # Only the incident whose file holds /scan messages: not the one where /scan was silent.
    status, html = dashboard.render("/incidents", "topic=/scan")
    assert status == 200 and len(_rows(html)) == 1
    # with what its window lost, as the record counts it
    assert "/scan: 150 messages, 849.6 KiB, 2 let go by the memory bound, 3 lost in transport" in _rows(html)[0]
    assert 'value="/scan"' in html and 'id="topic-search"' in html
    # Part of a name, any case, with the other filters.
    status, html = dashboard.render("/incidents", "topic=ODO")
    assert status == 200 and len(_rows(html)) == 3
    status, html = dashboard.render("/incidents", "topic=odom&reason=bumper&robot=C3PO")
    assert status == 200 and len(_rows(html)) == 1 and "service, bumper hit" in html
    # A topic recorded as absent is in no file; a _ is taken literally.
    for text in ("/camera", "/od_m"):
        status, html = dashboard.render("/incidents", f"topic={text}")
        assert status == 200 and not _rows(html)
        assert f"no incident with messages of a topic holding {text} for these filters" in html


def test_an_incident_file_downloads_through_the_dashboard_and_only_an_mcap_file(servers: Servers) -> None:
    server = make_server(DashboardSettings(servers.postgres, servers.s3), "127.0.0.1", 0, quiet=True)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        with urllib.request.urlopen(base + "/incidents?robot=C3PO", timeout=30) as response:
            html = response.read().decode()
        link = '<a class="download" href="/incident-file?key=C3PO%2Fincidents%2Fa.mcap" download>a.mcap</a>'
        assert link in html
        with urllib.request.urlopen(base + "/incident-file?key=C3PO%2Fincidents%2Fa.mcap", timeout=30) as response:
            assert response.read() == servers.mcap
            assert response.headers["Content-Disposition"] == 'attachment; filename="a.mcap"'
        # An object that is not an MCAP file, one that is missing, a key that is not an incident file's.
        for key in ("C3PO%2Fincidents%2Fb.mcap", "R2D2%2Fincidents%2Fc.mcap", "C3PO%2Fmap.png"):
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(base + "/incident-file?key=" + key, timeout=30)
            assert refused.value.code == 404
        # A browser that leaves in the middle of a large file: the dashboard goes on serving.
        connection = http.client.HTTPConnection("127.0.0.1", server.server_address[1], timeout=30)
        connection.request("GET", "/incident-file?key=C3PO%2Fincidents%2Fbig.mcap")
        response = connection.getresponse()
        assert response.status == 200 and int(response.headers["Content-Length"]) == BIG + 8
        assert response.read(1024)[:8] == servers.mcap[:8]
        connection.close()
        with urllib.request.urlopen(base + "/incidents", timeout=30) as response:
            assert response.status == 200
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5.0)


def test_the_incidents_page_in_a_browser_searches_by_reason(servers: Servers, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    from tests.test_dashboard import _browser, _screenshot

    server = make_server(DashboardSettings(servers.postgres, servers.s3), "127.0.0.1", 0, quiet=True)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    browser = _browser()
    try:
        browser.get(f"http://127.0.0.1:{server.server_address[1]}/incidents")
        assert len(browser.find_elements(By.CSS_SELECTOR, "tr.incident")) == 3
        assert browser.find_element(By.CSS_SELECTOR, "nav a.active, a.active").text == "Incidents"
        _screenshot(browser, tmp_path, "incidents")
        # Searching by a reason, as a user types it: the page keeps the incidents with it.
        browser.find_element(By.ID, "reason-search").send_keys("BUMPER")
        browser.find_element(By.ID, "reason-search").submit()
        WebDriverWait(browser, 30).until(lambda b: "reason=BUMPER" in b.current_url)
        reasons = [e.text for e in browser.find_elements(By.CSS_SELECTOR, "tr.incident td.reasons")]
        assert reasons == ["service, bumper hit", "operator: Bumper"]
        link = browser.find_element(By.CSS_SELECTOR, "tr.incident a.download")
        assert link.get_attribute("href").endswith("/incident-file?key=C3PO%2Fincidents%2Fb.mcap")
    finally:
        browser.quit()
        server.shutdown()
        server.server_close()
        thread.join(5.0)
