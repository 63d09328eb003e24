"""`dc demo` (make demo) as a user runs it: one command, the dashboard shows the robot's path and an
inspected shelf image, every page real data and no false alarm, and Ctrl-C leaves no process behind."""

from __future__ import annotations

import html
import os
import re
import shutil
import signal
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from dc_bringup.local_servers import postgres, seaweedfs
from dc_bringup.local_servers.processes import alive, free_port
from tests.bringup_util import BIN
from tests.domains import fresh_domain_id

pytestmark = pytest.mark.e2e


@pytest.fixture
def state_dir() -> Iterator[Path]:
    for missing in (postgres.missing_reason(), seaweedfs.missing_reason()):
        if missing is not None:
            pytest.skip(missing)
    # Not under tmp_path, and enterable by others: as root, PostgreSQL runs as the postgres user.
    folder = Path(tempfile.mkdtemp(prefix="dc-demo-"))
    folder.chmod(0o755)
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def _get(url: str) -> tuple[bytes, str]:
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.read(), response.headers.get_content_type()
    except OSError:
        return b"", ""


def _trajectory_points(base: str) -> int:
    page = _get(base + "/")[0].decode()
    trajectory = page.partition('<svg id="trajectory"')[2]
    return sum(int(n) for n in re.findall(r'<polyline class="series" data-points="(\d+)"', trajectory))


def _an_inspected_image(base: str) -> bool:
    page = _get(base + "/camera")[0].decode()
    for source in re.findall(r'<img class="inspected"[^>]* src="([^"]+)"', page):
        body, content_type = _get(base + html.unescape(source))
        if content_type == "image/jpeg" and body.startswith(b"\xff\xd8"):
            return True
    return False


def _false_alarms(base: str) -> list[str]:
    """What a page of the demo shows that is not real data, or alarms in a healthy run."""
    found = []
    overview = _get(base + "/")[0].decode()
    if "not collected" in overview or 'id="stat-distance"><span class="value">0.0 m' in overview:
        found.append("Overview: no distance traveled")
    system = _get(base + "/system")[0].decode()
    for chart in ("cpu-chart", "memory-chart"):
        if f'<svg id="{chart}" class="chart empty"' in system or f'id="{chart}"' not in system:
            found.append(f"System: {chart} empty")
    health = _get(base + "/health")[0].decode()
    if "indexes the dashboard needs" in health:
        found.append("Health: the missing-index banner")
    # destination, health, received, sent, pending, oldest pending, retried, failed: ok and 0 failed.
    for destination in ("flb_pgsql", "flb_minio", "flb_files_metrics"):
        row = re.search(
            rf"<tr><td>{destination}</td><td>(.*?)</td>(?:<td class=num>[^<]*</td>){{5}}<td class=num>([^<]*)</td>",
            health,
        )
        if row is None or "health ok" not in row.group(1) or row.group(2) != "0":
            found.append(f"Health: {destination} {row.groups() if row else 'absent'}")
    return found


def _descendants(pid: int) -> set[int]:
    """Every process below ``pid``, from /proc's children lists."""
    found: set[int] = set()
    parents = [pid]
    while parents:
        parent = parents.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                children = {int(c) for c in (task / "children").read_text().split()}
            except OSError:
                continue
            parents += children - found
            found |= children
    return found


def test_dc_demo_shows_the_qr_demo_in_the_dashboard_and_stops_everything(tmp_path: Path, state_dir: Path) -> None:
    home = tmp_path / "home"
    home.mkdir()
    env = dict(os.environ, HOME=str(home), XDG_DATA_HOME=str(home / ".local" / "share"))
    env["ROS_DOMAIN_ID"] = str(fresh_domain_id())
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    # --duration: a safety net only; the test stops it with SIGINT, as Ctrl-C would.
    command = [str(BIN / "dc"), "demo", "--duration", "240", "--port", str(port), "--state-dir", str(state_dir)]
    demo = subprocess.Popen(
        [*command, "--rate", "2"], cwd=home, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    output: list[str] = []
    reader = threading.Thread(target=lambda: output.extend(demo.stdout or []), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        points = inspected = every_page = False
        while not (points and inspected and every_page) and demo.poll() is None and time.monotonic() < deadline:
            time.sleep(1)
            points = points or _trajectory_points(base) > 0
            inspected = inspected or (points and _an_inspected_image(base))
            every_page = every_page or (inspected and not _false_alarms(base))
        assert points and inspected, f"trajectory {points}, inspected image {inspected}\n" + "".join(output)
        assert every_page, "\n".join(_false_alarms(base)) + "\n" + "".join(output)
        # The destination server's metrics are on: the health page has its last delivery.
        health = _get(base + "/health")[0].decode()
        assert re.search(r'id="stat-last-delivery"><span class="value">[\d,]+ s ago', health), health
        started = _descendants(demo.pid)
        postmaster = (state_dir / "servers" / "postgres" / "data" / "postmaster.pid").read_text().split()[0]
        demo.send_signal(signal.SIGINT)
        code = demo.wait(90)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    reader.join(5)
    text = "".join(output)
    assert code == 0, text
    assert f"open http://127.0.0.1:{port}/" in text and str(state_dir) in text
    # The sim, dc-bringup and its servers, the dashboard, SeaweedFS; PostgreSQL, started by pg_ctl, is no child.
    assert len(started) >= 5, started
    assert not [pid for pid in [*started, int(postmaster)] if alive(pid)], text
    for log in ("sim.log", "dc-bringup.log", "dashboard.log"):
        assert (state_dir / log).stat().st_size > 0, log
