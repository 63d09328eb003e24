"""A camera password given to DC reaches the camera and nothing else: no log, no file, no command line.

One dc-bringup run records two IP cameras: one that asks for the password (HTTP Basic, as many
cameras do) and streams once given it, one whose port refuses connections (ffmpeg restarted again
and again, each restart logged with ffmpeg's last message). Every form of both passwords is then
looked for in each process' command line and environment during the run, and after it in
everything the run printed and in every file it wrote (ROS logs, ffmpeg's log, the buffer, the
segments, the File destination's output). The same run shows the modes of what DC wrote.
"""

from __future__ import annotations

import base64
import os
import shutil
import socket
import stat
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest

from tests.bringup_util import Bringup

pytestmark = pytest.mark.e2e

if shutil.which("ffmpeg") is None:
    pytest.skip("ffmpeg is not installed (Debian package ffmpeg)", allow_module_level=True)

USER = "viewer"
# Characters a URL must percent-encode and ffmpeg's concat script must quote.
PASSWORD = "Pa'ss w#rd%9-secret-1"
REFUSED_PASSWORD = "other-Secret-2"


def forms(user: str, password: str) -> list[bytes]:
    """Every way a password may be written down: as typed, percent-encoded, in a Basic auth header."""
    texts = {
        password,
        quote(password, safe=""),
        quote(password),
        base64.b64encode(f"{user}:{password}".encode()).decode(),
    }
    return [text.encode() for text in texts]


SECRETS = forms(USER, PASSWORD) + forms(USER, REFUSED_PASSWORD)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class AuthCamera:
    """A camera that streams MPEG-TS over HTTP only to a client with its password (Basic auth)."""

    def __init__(self, user: str, password: str) -> None:
        self.expected = "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()
        self.authorised = 0
        self.refused = 0
        camera = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                if self.headers.get("Authorization") != camera.expected:
                    camera.refused += 1
                    self.send_response(401)
                    self.send_header("WWW-Authenticate", 'Basic realm="camera"')
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                camera.authorised += 1
                self.send_response(200)
                self.send_header("Content-Type", "video/mp2t")
                self.end_headers()
                camera.stream(self.wfile)

            def log_message(self, format: str, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.port = self.server.server_address[1]
        self.url = f"http://{USER}:{quote(password, safe='')}@127.0.0.1:{self.port}/cam.ts"
        self._encoders: list[subprocess.Popen[bytes]] = []

    def stream(self, out: Any) -> None:
        # A keyframe a second: the recorder starts decoding at once.
        source = ["-re", "-f", "lavfi", "-i", "testsrc=size=320x240:rate=10"]
        encoding = ["-c:v", "libx264", "-preset", "ultrafast", "-g", "10", "-f", "mpegts", "pipe:1"]
        encoder = subprocess.Popen(
            ["ffmpeg", "-nostdin", "-loglevel", "error", *source, *encoding],
            stdout=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
        )
        self._encoders.append(encoder)
        assert encoder.stdout is not None
        try:
            while chunk := os.read(encoder.stdout.fileno(), 65536):
                out.write(chunk)
        except OSError:
            pass  # the recorder went away
        finally:
            encoder.kill()
            encoder.wait()

    def __enter__(self) -> AuthCamera:
        threading.Thread(target=self.server.serve_forever, daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.shutdown()
        self.server.server_close()
        for encoder in self._encoders:
            encoder.kill()
            encoder.wait()


@dataclass
class Run:
    home: Path
    roslog: Path
    out_file: Path
    bringup: Bringup
    camera: AuthCamera
    # (pid, what) for each process whose command line or environment held a password during the run.
    seen_in_processes: list[tuple[int, str]] = field(default_factory=list)
    ffmpeg_command_lines: list[str] = field(default_factory=list)


def segments_delivered(run: Run) -> list[str]:
    if not run.out_file.exists():
        return []
    return [line for line in run.out_file.read_text().splitlines() if '"data_src":"camera"' in line]


def scan_processes(run: Run) -> None:
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        for what in ("cmdline", "environ"):
            try:
                content = (entry / what).read_bytes()
            except OSError:
                continue  # gone, or another user's environment
            if any(secret in content for secret in SECRETS):
                run.seen_in_processes.append((int(entry.name), f"{what}: {content[:300]!r}"))
            # A recorder of this run (other test sessions on the machine may record too).
            if what == "cmdline" and b"-hls_time" in content and str(run.home).encode() in content:
                run.ffmpeg_command_lines.append(content.replace(b"\0", b" ").decode(errors="replace"))


PARAMS = """
destination_server:
  ros__parameters:
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/File"
      inputs: ["/dc/measurement/camera", "/dc/measurement/refused"]
      path: "{out}"
      file: "records.jsonl"
measurement_server:
  ros__parameters:
    measurement_plugins: ["camera", "refused"]
    save_local_base_path: "{data}"
    camera:
      plugin: "dc_measurements/IpCamera"
      topic_output: "/dc/measurement/camera"
      tags: ["out"]
      polling_interval: 500
      input: "{camera}"
      segment_time: 1
      save_path: "camera/%H%M%S"
    refused:
      plugin: "dc_measurements/IpCamera"
      topic_output: "/dc/measurement/refused"
      tags: ["out"]
      polling_interval: 500
      input: "{refused}"
      segment_time: 1
"""


@pytest.fixture(scope="module", params=["processes", "single-process"])
def run(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    """One run per dc-bringup mode: the umask is set in the supervisor and in each server process."""
    mode_args = ["--single-process"] if request.param == "single-process" else []
    home = tmp_path_factory.mktemp("secrets")
    roslog = home / "roslog"
    out = home / "out"
    params = home / "params.yaml"
    refused = f"rtsp://{USER}:{quote(REFUSED_PASSWORD, safe='')}@127.0.0.1:{free_port()}/stream"
    with AuthCamera(USER, PASSWORD) as camera:
        params.write_text(PARAMS.format(out=out, data=home / "data", camera=camera.url, refused=refused))
        with Bringup(params, home, args=mode_args, env={"ROS_LOG_DIR": str(roslog)}) as bringup:
            state = Run(home, roslog, out / "records.jsonl", bringup, camera)
            bringup.wait_ready(60)
            # Watch the processes while the recorders run and restart, until three segments are delivered.
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                scan_processes(state)
                delivered = len(segments_delivered(state))
                restarts = sum("refused: ffmpeg exited" in line for line in bringup.stderr)
                if delivered >= 3 and restarts >= 2:
                    break
                time.sleep(0.2)
            else:
                raise AssertionError("no 3 segments and 2 restarts in 60 s:\n" + "\n".join(bringup.stderr[-40:]))
        assert bringup.returncode == 0, "\n".join(bringup.stderr[-40:])
        yield state


def test_the_password_reaches_the_camera(run: Run) -> None:
    assert run.camera.authorised >= 1
    assert len(segments_delivered(run)) >= 3


def test_no_process_shows_a_password_on_its_command_line_or_in_its_environment(run: Run) -> None:
    assert run.ffmpeg_command_lines, "the recorders' ffmpeg was never seen running"
    assert all("pipe:0" in line for line in run.ffmpeg_command_lines), run.ffmpeg_command_lines[:2]
    assert run.seen_in_processes == []


def test_no_log_and_no_file_of_the_run_holds_a_password(run: Run) -> None:
    printed = "\n".join(run.bringup.stdout + run.bringup.stderr).encode()
    assert not [s for s in SECRETS if s in printed], "a password was printed"
    # What DC told about the refused camera, with the password masked.
    warnings = [line for line in run.bringup.stderr if "refused: ffmpeg exited" in line]
    assert any("Connection refused" in line and f"{USER}:***@127.0.0.1" in line for line in warnings), warnings
    ffmpeg_log = run.home / "data" / "tmp" / "refused.ffmpeg.log"
    assert b"Connection refused" in ffmpeg_log.read_bytes()
    written = [path for path in run.home.rglob("*") if path.is_file() and path.name != "params.yaml"]
    assert any(path.is_relative_to(run.roslog) for path in written), "the run wrote no ROS log"
    holding = [str(path) for path in written if any(s in path.read_bytes() for s in SECRETS)]
    assert holding == []


def test_what_the_run_wrote_is_its_users_alone(run: Run) -> None:
    def mode(path: Path) -> int:
        return stat.S_IMODE(path.stat().st_mode)

    tmp = run.home / "data" / "tmp"
    assert mode(tmp) == mode(tmp / "camera") == 0o700
    assert mode(tmp / "camera.ffmpeg.log") == mode(tmp / "refused.ffmpeg.log") == 0o600
    segments = list((run.home / "data" / "camera").glob("*.ts"))
    assert segments and {mode(path) for path in segments} == {0o600}
    buffer_files = list((run.home / ".local" / "share" / "dc").rglob("*"))
    folders = {mode(path) for path in buffer_files if path.is_dir()}
    files = {path.name: mode(path) for path in buffer_files if path.is_file()}
    assert folders == {0o700}
    assert "delivery.sqlite3" in files and "delivery.sqlite3.lock" in files
    assert set(files.values()) == {0o600}, files
    assert mode(run.out_file) == 0o600 and mode(run.out_file.parent) == 0o700
    ros_logs = [path for path in run.roslog.rglob("*") if path.is_file()]
    assert ros_logs and {mode(path) for path in ros_logs} == {0o600}
