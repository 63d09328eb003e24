"""IpCamera against a real stream: a camera stand-in served by ffmpeg over HTTP on loopback.

What a user relies on: finished segments of the configured length, each published once as a
readable MPEG-TS file; a stream that drops and comes back is recorded again without a crash; no
ffmpeg is left behind by a stop or by a ``kill -9`` of the server; bad parameters are refused at
configure with the key named.
"""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest

from dc_core.errors import ConfigError, DcError, PluginError
from dc_core.measurement import BasePaths
from dc_core.testing import PluginHarness
from dc_measurements.ip_camera import IpCamera, IpCameraParams, ffmpeg
from dc_measurements.ip_camera.ffmpeg import Recording, ScrubbedLog, Scrubber, read_playlist, without_password
from tests.measurement_helpers import assert_valid

if shutil.which("ffmpeg") is None or shutil.which("ffprobe") is None:
    pytest.skip("ffmpeg and ffprobe are not installed (Debian package ffmpeg)", allow_module_level=True)

REPO = Path(__file__).resolve().parents[2]
SEGMENT_S = 1


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class Camera:
    """A camera stand-in: ffmpeg serving a test pattern as MPEG-TS over HTTP, to one client."""

    def __init__(self) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}/cam.ts"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        # A keyframe a second: a client that connects any time starts decoding quickly.
        source = ["-re", "-f", "lavfi", "-i", "testsrc=size=320x240:rate=10"]
        encoding = ["-c:v", "libx264", "-preset", "ultrafast", "-g", "10"]
        for attempt in range(3):
            self.process = subprocess.Popen(
                [
                    "ffmpeg",
                    "-nostdin",
                    "-loglevel",
                    "error",
                    *source,
                    *encoding,
                    "-f",
                    "mpegts",
                    "-listen",
                    "1",
                    self.url,
                ],
                stdin=subprocess.DEVNULL,
            )
            # Ready once it listens (or serves); a test connection would take the one client it serves.
            process = self.process
            wait_for(
                "the camera listening, or exiting",
                lambda p=process: p.poll() is not None or self._listens(p.pid),  # type: ignore[misc]
                30,
            )
            if process.poll() is None:
                return
            # Started again on the port of a camera just killed, ffmpeg may find it still taken.
            time.sleep(0.5 * (attempt + 1))
        raise AssertionError(f"the camera's ffmpeg kept exiting (code {process.returncode})")

    def _listens(self, pid: int) -> bool:
        try:
            connections = psutil.Process(pid).net_connections()
        except psutil.Error:  # exited between the poll and this look
            return False
        # With -listen 1 ffmpeg closes its listening socket once a client is in: a recorder that
        # reconnects the moment it listens leaves only the established connection to see.
        serving = (psutil.CONN_LISTEN, psutil.CONN_ESTABLISHED)
        return any(c.status in serving and c.laddr.port == self.port for c in connections)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()


@pytest.fixture
def camera() -> Iterator[Camera]:
    cam = Camera()
    cam.start()
    try:
        yield cam
    finally:
        cam.stop()


@pytest.fixture
def harness() -> Iterator[PluginHarness]:
    h = PluginHarness()
    yield h
    for plugin_id in list(h.contexts):
        context = h.contexts.pop(plugin_id)
        context.stop_worker()


def make(harness: PluginHarness, base: Path, name: str = "cam", **values: Any) -> IpCamera:
    plugin = harness.make(IpCamera, {"segment_time": SEGMENT_S, **values}, name=name)
    harness.context(plugin).paths = BasePaths(
        save_local_base_path=str(base / "data" / "%Y"), all_base_path="robot", remote_prefixes={"minio": "videos"}
    )
    plugin.on_configure()
    return plugin


def wait_for(what: str, get: Callable[[], Any], timeout: float) -> Any:
    """``get()`` once it is truthy, polled until ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = get()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what}: not within {timeout} s")


def probe(path: str) -> dict[str, Any]:
    done = subprocess.run(
        ["ffprobe", "-v", "error", "-show_entries", "format=format_name,duration", "-of", "json", path],
        capture_output=True,
        text=True,
        check=True,
    )
    fmt: dict[str, Any] = json.loads(done.stdout)["format"]
    return fmt


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def test_each_poll_publishes_one_finished_segment_of_segment_time(
    camera: Camera, harness: PluginHarness, tmp_path: Path
) -> None:
    plugin = make(harness, tmp_path, input=camera.url)
    plugin.on_activate()
    try:
        records: list[dict[str, Any]] = []
        deadline = time.monotonic() + 40
        while len(records) < 4 and time.monotonic() < deadline:
            record = plugin.collect()
            if record is not None:
                records.append(record)
            else:
                time.sleep(0.2)
        assert len(records) >= 4, f"only {len(records)} segments in 40 s"
    finally:
        harness.stop(plugin)

    paths = [r["local_path"] for r in records]
    assert len(set(paths)) == len(paths), "a segment was published twice"
    for record in records:
        assert_valid(IpCamera, record)
        assert record["data_src"] == "cam"
        path = record["local_path"]
        assert path.startswith(str(tmp_path / "data")) and path.endswith(".ts")
        assert os.path.isfile(path)
        assert record["remote_path"] == path.split(f"{tmp_path}/data/{time.strftime('%Y')}/", 1)[1]
        assert record["remote_paths"] == {"minio": "robot/videos/" + os.path.basename(path)}
        assert abs(record["duration"] - SEGMENT_S) < 0.35
        fmt = probe(path)
        assert fmt["format_name"] == "mpegts"
        assert abs(float(fmt["duration"]) - SEGMENT_S) < 0.5, fmt
    starts = [r["timestamp"] for r in records]
    assert starts == sorted(starts), "segments are published oldest first"
    assert plugin.counters()["segments"] == len(records)


def test_a_stream_that_drops_is_recorded_again_after_backoff(camera: Camera, tmp_path: Path) -> None:
    harness = PluginHarness()
    plugin = make(harness, tmp_path, input=camera.url)
    plugin.on_activate()
    logger = harness.context(plugin).logger
    try:
        wait_for("a first segment", plugin.collect, 40)
        first_pid = plugin.ffmpeg_pid
        camera.stop()
        # Exit at the end of the stream, then refused connections: restarted after 1 s, then 2 s.
        wait_for("two restarts", lambda: plugin.counters()["restarts"] >= 2, 20)
        warnings = logger.at("warning")
        assert "exited with code 0" in warnings[0] and "the stream ended" in warnings[0], warnings
        assert "Connection refused" in warnings[1] and "restarting in 2 s" in warnings[1], warnings
        restarts = plugin.counters()["restarts"]
        while plugin.collect() is not None:  # what was recorded before the drop
            pass
        camera.start()
        record = wait_for("a segment after the stream came back", plugin.collect, 60)
        assert_valid(IpCamera, record)
        assert plugin.counters()["restarts"] >= restarts
        assert plugin.ffmpeg_pid not in (None, first_pid)
        assert not logger.at("error")
    finally:
        harness.stop(plugin)


def test_deactivate_stops_ffmpeg_and_the_next_start_publishes_what_was_left(
    camera: Camera, harness: PluginHarness, tmp_path: Path
) -> None:
    plugin = make(harness, tmp_path, input=camera.url)
    plugin.on_activate()
    pid = wait_for("ffmpeg running", lambda: plugin.ffmpeg_pid, 10)
    wait_for("a finished segment", lambda: any(n.endswith(".ts") for n in os.listdir(plugin.folder)), 40)
    plugin.on_deactivate()
    assert gone(pid), "ffmpeg still runs after deactivate"
    assert plugin.ffmpeg_pid is None
    plugin.on_cleanup()
    left = sorted(n for n in os.listdir(plugin.folder) if n.endswith(".ts"))
    assert left

    # The next run (camera gone) still publishes them: nothing recorded is lost.
    camera.stop()
    again = make(harness, tmp_path, input=camera.url)
    again.on_activate()
    try:
        published = list(iter(again.collect, None))
        assert len(published) == len(left)
        for record in published:
            assert_valid(IpCamera, record)
            assert probe(record["local_path"])["format_name"] == "mpegts"
        assert not [n for n in os.listdir(again.folder) if n.endswith(".ts")]
    finally:
        again.on_deactivate()
        again.on_cleanup()


CHILD = textwrap.dedent(
    """
    import sys, time
    from dc_core.measurement import BasePaths
    from dc_core.testing import PluginHarness
    from dc_measurements.ip_camera import IpCamera, IpCameraParams

    harness = PluginHarness()
    plugin = harness.make(IpCamera, {"input": sys.argv[1], "segment_time": 1}, name="cam")
    harness.context(plugin).paths = BasePaths(save_local_base_path=sys.argv[2])
    plugin.on_configure()
    plugin.on_activate()
    while plugin.ffmpeg_pid is None:
        time.sleep(0.05)
    print(plugin.ffmpeg_pid, flush=True)
    time.sleep(600)
    """
)


def test_kill_9_of_the_server_process_leaves_no_ffmpeg(camera: Camera, tmp_path: Path) -> None:
    server = subprocess.Popen(
        [sys.executable, "-c", CHILD, camera.url, str(tmp_path)], stdout=subprocess.PIPE, text=True, cwd=REPO
    )
    try:
        assert server.stdout is not None
        pid = int(server.stdout.readline())
        assert psutil.Process(pid).name() == "ffmpeg"
        assert psutil.Process(pid).ppid() == server.pid
        server.send_signal(signal.SIGKILL)
        server.wait()
        wait_for("ffmpeg gone after kill -9 of its parent", lambda: gone(pid), 10)
    finally:
        server.kill()
        server.wait()


@pytest.mark.parametrize(
    ("values", "key"),
    [
        ({"bitrate_video": "fast"}, "bitrate_video"),
        ({"bitrate_audio": "1.5M"}, "bitrate_audio"),
        ({"ffmpeg_log_level": "loud"}, "ffmpeg_log_level"),
        ({"segment_time": 0}, "segment_time"),
        ({"video": False, "audio": False}, "video"),
        ({"save_path": ""}, "save_path"),
        ({"input": "rtsp://"}, "input"),
        ({"input": "/no/such/camera.ts"}, "input"),
        ({"input": None}, "input"),
    ],
)
def test_a_bad_parameter_is_refused_at_configure_naming_it(
    values: dict[str, Any], key: str, harness: PluginHarness, tmp_path: Path
) -> None:
    params = {"input": "rtsp://192.168.0.10:554/stream", **values}
    if params["input"] is None:
        del params["input"]
    with pytest.raises(DcError, match=key) as raised:
        make(harness, tmp_path, **params)
    if isinstance(raised.value, ConfigError):
        assert raised.value.path.endswith(f".cam.{key}")


def test_configure_says_when_ffmpeg_is_not_installed(
    harness: PluginHarness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(PluginError, match="ffmpeg is not installed"):
        make(harness, tmp_path, input="rtsp://192.168.0.10:554/stream")


def test_a_colon_in_save_path_is_fine_and_the_playlist_is_read() -> None:
    # ffmpeg never sees save_path (segments are renamed by DC), so the default's ':' is kept.
    assert ":" in IpCameraParams(input="rtsp://camera/stream").save_path
    listed = read_playlist(
        "#EXTM3U\n#EXTINF:1.000000,\n#EXT-X-PROGRAM-DATE-TIME:2024-03-01T10:15:42.090+0100\n1_00000.ts\n"
    )
    assert listed["1_00000.ts"].duration_s == 1.0
    assert listed["1_00000.ts"].start_s == pytest.approx(1709284542.09)
    assert without_password("rtsp://admin:secret@10.0.0.5:554/s") == "rtsp://admin:***@10.0.0.5:554/s"


SECRET_URL = "rtsp://admin:p%40ss%27word@10.0.0.5:554/live?channel=1&token=T0KEN-42"


def test_the_stream_url_is_given_on_stdin_never_on_the_command_line() -> None:
    recording = Recording(
        input=SECRET_URL,
        video=True,
        audio=False,
        bitrate_video="1M",
        bitrate_audio="128k",
        segment=True,
        segment_time=1,
        log_level="info",
        banner=False,
    )
    command = ffmpeg.command("/usr/bin/ffmpeg", recording, "/data/tmp/cam", "1")
    assert command[command.index("-i") + 1] == "pipe:0"
    assert not [arg for arg in command if "10.0.0.5" in arg or "p%40ss" in arg]
    # What ffmpeg reads there: the URL, its quote escaped as the concat script wants it.
    script = ffmpeg.concat_script("rtsp://a:it's@cam/s").decode()
    assert script == "ffconcat version 1.0\nfile 'rtsp://a:it'\\''s@cam/s'\n"
    from_file = ffmpeg.command("/usr/bin/ffmpeg", dataclasses.replace(recording, input="/videos/test.ts"), "/t", "1")
    assert from_file[from_file.index("-i") + 1] == "/videos/test.ts"


def test_every_form_of_the_password_is_masked_in_what_ffmpeg_writes() -> None:
    scrub = Scrubber(SECRET_URL).scrub
    basic = base64.b64encode(b"admin:p@ss'word").decode()
    lines = {
        "[concat @ 0x5] Impossible to open 'rtsp://admin:p%40ss%27word@10.0.0.5:554/live?channel=1&token=T0KEN-42'": (
            "[concat @ 0x5] Impossible to open 'rtsp://admin:***@10.0.0.5:554/live?channel=1&token=***'"
        ),
        f"Authorization: Basic {basic}": "Authorization: Basic ***",
        "password p@ss'word in plain, p%40ss%27word encoded": "password *** in plain, *** encoded",
        "redirected to http://someone:else@other/": "redirected to http://someone:***@other/",
        "pipe:0: Connection refused": "rtsp://admin:***@10.0.0.5:554/live?channel=1&token=***: Connection refused",
        "Input #0, concat, from 'pipe:0':": "Input #0, concat, from 'pipe:0':",
    }
    for line, masked in lines.items():
        assert scrub(line) == masked
    assert without_password(SECRET_URL) == "rtsp://admin:***@10.0.0.5:554/live?channel=1&token=***"


def test_ffmpegs_messages_are_written_scrubbed_whole_lines_only() -> None:
    read_end, write_end = os.pipe()
    log = io.BytesIO()
    messages = ScrubbedLog(os.fdopen(read_end, "rb"), log, Scrubber("http://u:hunter2@cam/s"))

    def feed(data: bytes) -> None:
        for start in range(0, len(data), 8192):  # within the pipe's buffer, read as it comes
            os.write(write_end, data[start : start + 8192])
            messages.pump(0.1)

    # The password split between two writes is still masked: a line is scrubbed once complete.
    feed(b"first line with hun")
    assert log.getvalue() == b""
    feed(b"ter2 inside\n" + b"x" * (ffmpeg.MAX_LINE + 20000) + b"hunter2 beyond the cut\nlast: hunter2")
    os.close(write_end)
    messages.drain()
    lines = log.getvalue().split(b"\n")
    assert lines[0] == b"first line with *** inside"
    assert lines[1].endswith(b"x [line cut]") and len(lines[1]) < ffmpeg.MAX_LINE + 20
    assert lines[2] == b"last: ***"
    assert b"hunter2" not in log.getvalue()
    assert messages.last_line == "last: ***"


def test_a_bad_url_is_refused_with_its_password_masked(harness: PluginHarness, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"got \"rtsp://admin:\*\*\*@cam/a b\"") as raised:
        make(harness, tmp_path, input="rtsp://admin:hunter2@cam/a b")
    assert "hunter2" not in str(raised.value)
    with pytest.raises(PluginError, match=r"'admin:\*\*\*@cam/stream' is neither a URL") as refused:
        make(harness, tmp_path, input="admin:hunter2@cam/stream")
    assert "hunter2" not in str(refused.value)


def test_ffmpegs_log_is_0600_in_a_0700_folder_even_when_an_older_dc_left_it_open(
    camera: Camera, harness: PluginHarness, tmp_path: Path
) -> None:
    (tmp_path / "data" / "tmp").mkdir(parents=True)
    old_log = tmp_path / "data" / "tmp" / "cam.ffmpeg.log"
    old_log.write_text("rtsp://admin:hunter2@camera: Connection refused\n")
    old_log.chmod(0o644)
    plugin = make(harness, tmp_path, input=camera.url)
    plugin.on_activate()
    try:
        wait_for("a first segment", plugin.collect, 40)
    finally:
        harness.stop(plugin)
    assert stat.S_IMODE(old_log.stat().st_mode) == 0o600
    assert stat.S_IMODE(os.stat(plugin.folder).st_mode) == 0o700


def test_a_pipe_held_open_after_ffmpeg_exited_does_not_hold_its_supervisor(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ffmpeg, "DRAIN_S", 0.5)
    # The shell exits at once; the sleep it started keeps the stderr pipe open for 30 s.
    process = ffmpeg.start(["sh", "-c", "sleep 30 & echo 'failed: http://u:hunter2@cam/s' >&2; exit 3"], None)
    assert process.stderr is not None
    log = io.BytesIO()
    messages = ScrubbedLog(process.stderr, log, Scrubber("http://u:hunter2@cam/s"))
    started = time.monotonic()
    try:
        assert ffmpeg.wait(process, messages, 10) == 3
        assert time.monotonic() - started < 3
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # the sleep, in ffmpeg's process group
    assert messages.closed and messages.last_line == "failed: http://u:***@cam/s"
