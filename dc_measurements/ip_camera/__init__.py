"""IpCamera measurement: an IP camera's stream recorded by ffmpeg in segments, one published per poll.

Connecting to a camera takes seconds, so the recording is not started by a poll: ffmpeg runs from
activation to deactivation and writes HLS segments (MPEG-TS files of ``segment_time`` seconds)
into a temporary folder. A poll takes the oldest *finished* segment there, moves it to its final
path and publishes where it is. A segment is finished when it has its ``.ts`` name: ffmpeg writes
each one under ``<name>.ts.tmp`` and renames it only once it is complete (``-hls_flags
temp_file``), so a record never points at half a file.

ffmpeg is supervised by a thread that lives as long as the recording: when the stream goes down
and ffmpeg exits (or stops writing), it is started again after 1 s, 2 s, 4 s… up to 60 s. ffmpeg
is started from that thread with PR_SET_PDEATHSIG, so even a ``kill -9`` of the server leaves no
ffmpeg behind (the signal fires when the thread that forked the child ends, hence never from a
short-lived worker job). The original started ffmpeg detached, never restarted nor stopped it.

The camera's password reaches neither ffmpeg's command line nor a log: the URL goes to ffmpeg on
its stdin and everything ffmpeg writes is read by DC and scrubbed before it reaches the log file
(:mod:`dc_measurements.ip_camera.ffmpeg`). That file is created 0600, its folder 0700.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from dc_core.errors import ConfigError, PluginError
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param
from dc_core.paths import expand_time, fixed_prefix
from dc_core.private_files import create_private, make_folders, tighten
from dc_measurements.ip_camera import ffmpeg
from dc_measurements.saved_files import ReservedPaths, file_locations


def _input_problem(value: str) -> str | None:
    if not value.strip():
        return "a stream URL (scheme://host/…) or the path of a file"
    return None


def _bitrate_problem(value: str) -> str | None:
    return None if ffmpeg.BITRATE.match(value) else "a bitrate: digits and an optional k or M (2M, 500k, 128000)"


def _save_path_problem(value: str) -> str | None:
    if not value.strip() or value.endswith("/"):
        return "a file path without extension, not ending with /"
    return None


@dataclass(frozen=True, kw_only=True)
class IpCameraParams:
    input: str = param(doc="Stream URL (rtsp://, http://, udp://…) or file ffmpeg reads", check=_input_problem)
    video: bool = param(True, doc="Record the video")
    audio: bool = param(False, doc="Record the audio")
    bitrate_video: str = param("2M", doc="Video bitrate (ffmpeg -b:v)", check=_bitrate_problem)
    bitrate_audio: str = param("192k", doc="Audio bitrate (ffmpeg -b:a)", check=_bitrate_problem)
    segment: bool = param(True, doc="Record in segments of segment_time seconds; false: one file per recording")
    segment_time: int = param(10, minimum=1, doc="Seconds per segment")
    ffmpeg_log_level: str = param("info", choices=ffmpeg.LOG_LEVELS, doc="ffmpeg -loglevel of its log file")
    ffmpeg_banner: bool = param(True, doc="ffmpeg's version banner at the top of each run in its log file")
    save_path: str = param(
        "ffmpeg_%Y-%m-%dT%H:%M:%S",
        doc="Path of a segment without .ts, under save_local_base_path/all_base_path (strftime: the segment's start)",
        check=_save_path_problem,
    )

    def __post_init__(self) -> None:
        if ffmpeg.is_url(self.input) and not ffmpeg.URL.match(self.input):
            # Checked here rather than by `check`: the message shows the URL with its password masked.
            shown = ffmpeg.without_password(self.input)
            raise ConfigError("input", f'expected a URL as scheme://host/path, without spaces, got "{shown}"')
        if not self.video and not self.audio:
            raise ConfigError("video", "video and audio are both false: there would be nothing to record")


@dataclass(frozen=True)
class _Segment:
    name: str
    session: str
    index: int
    unfinished: bool

    @property
    def final_name(self) -> str:
        return self.name.rsplit(".", 1)[0] if self.unfinished else self.name


class IpCamera(Measurement[IpCameraParams]):
    """IP camera stream recorded by ffmpeg in video segments; each poll publishes one finished segment."""

    # A poll moves a file, which may be a copy when the final folder is on another file system.
    collect_in_worker = True

    # Restart delays: doubled after each failure, back to the first once ffmpeg ran STABLE_RUN_S.
    RESTART_FIRST_S = 1.0
    RESTART_MAX_S = 60.0
    STABLE_RUN_S = 60.0
    # ffmpeg writing nothing for this long (or 3 segments' time) is stopped and started again.
    STALL_MIN_S = 30.0
    # How long ffmpeg may take to finish its segment when asked to stop, before SIGKILL.
    STOP_GRACE_S = 5.0
    LOG_ROTATE_BYTES = 10 * 1024 * 1024

    def __init__(self, context: MeasurementContext, params: IpCameraParams) -> None:
        super().__init__(context, params)
        self._executable = ""
        self.folder = ""
        self.log_path = ""
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._session: str | None = None
        self._last_session = 0
        self._listed: dict[str, ffmpeg.Listed] = {}
        self._reserved = ReservedPaths()
        self._scrubber = ffmpeg.Scrubber(params.input)
        self.restarts = 0
        self.segments = 0

    # -- lifecycle -----------------------------------------------------------------------------

    def on_configure(self) -> None:
        name, p = self.context.name, self.params
        executable = shutil.which("ffmpeg")
        if executable is None:
            raise PluginError(
                f"{name}: ffmpeg is not installed (not found on PATH); install it, e.g. `sudo apt-get install ffmpeg`"
            )
        self._executable = executable
        if "://" not in p.input and not os.path.exists(p.input):
            # "admin:pass@camera/stream" (a URL without its scheme) must not print its password either.
            shown = re.sub(r":[^@/]*@", ":***@", p.input)
            raise PluginError(f"{name}: input {shown!r} is neither a URL (scheme://…) nor an existing file")
        base = fixed_prefix(self.context.paths.save_local_base_path)
        self.folder = os.path.join(base, "tmp", name)
        self.log_path = self.folder + ".ffmpeg.log"

    def on_activate(self) -> None:
        try:
            make_folders(self.folder)
        except OSError as exc:
            raise PluginError(f"{self.context.name}: cannot create the temporary folder {self.folder}: {exc}") from exc
        # Written by an older DC 0644 with the password in it: the user's alone from now on.
        for log in (self.log_path, self.log_path + ".1"):
            tighten(log)
        self._stopping.clear()
        self.context.logger.info(
            f"{self.context.name}: recording {ffmpeg.without_password(self.params.input)} into {self.folder} "
            f"(ffmpeg's messages: {self.log_path})"
        )
        # Under the server's supervision rule: a bug here must not leave the camera silently unrecorded.
        self._supervisor = self.context.start_thread(self._supervise, name=f"{self.context.name}-ffmpeg")

    def on_deactivate(self) -> None:
        self._stop_recording()

    def on_cleanup(self) -> None:
        self._stop_recording()
        self._listed.clear()
        # An empty temporary folder is not left behind (one with segments waits for the next start).
        with contextlib.suppress(OSError):
            if self.folder:
                os.rmdir(self.folder)

    def counters(self) -> dict[str, int]:
        return {"restarts": self.restarts, "segments": self.segments}

    @property
    def ffmpeg_pid(self) -> int | None:
        """The pid of the running ffmpeg, if one runs."""
        with self._lock:
            return self._process.pid if self._process is not None else None

    def _stop_recording(self) -> None:
        self._stopping.set()
        supervisor, self._supervisor = self._supervisor, None
        if supervisor is not None:
            supervisor.join(self.STOP_GRACE_S + 5.0)
            if supervisor.is_alive():
                self.context.logger.error(f"{self.context.name}: ffmpeg did not stop in time")

    # -- the supervisor thread: starts ffmpeg, and again when it ends ------------------------

    def _supervise(self) -> None:
        delay = self.RESTART_FIRST_S
        while not self._stopping.is_set():
            started = time.monotonic()
            code, last_line = self._run_once()
            if self._stopping.is_set():
                return
            ran = time.monotonic() - started
            if ran >= self.STABLE_RUN_S:
                delay = self.RESTART_FIRST_S
            # Exit code 0: the camera closed the stream (its last line is then only statistics).
            why = "the stream ended" if code == 0 else last_line or "no message"
            self.context.logger.warning(
                f"{self.context.name}: ffmpeg exited with code {code} after {ran:.1f} s ({why}); "
                f"restarting in {delay:g} s (log: {self.log_path})"
            )
            if self._stopping.wait(delay):
                return
            delay = min(delay * 2, self.RESTART_MAX_S)
            with self._lock:
                self.restarts += 1

    def _new_session(self) -> str:
        # Epoch ms: sessions sort by start, and a leftover's session tells when it was recorded.
        session = max(time.time_ns() // 1_000_000, self._last_session + 1)
        self._last_session = session
        return str(session)

    def _run_once(self) -> tuple[int | str, str]:
        """One ffmpeg run until it exits or is stopped: its exit code (or why it did not start) and
        the last line of its messages."""
        session = self._new_session()
        cmd = ffmpeg.command(self._executable, self._recording(), self.folder, session)
        try:
            make_folders(self.folder)
            self._rotate_log()
            log = os.fdopen(create_private(self.log_path, os.O_WRONLY | os.O_APPEND), "ab")
        except OSError as exc:
            return "none", f"cannot open {self.log_path}: {exc}"
        with log:
            stamp = datetime.now().astimezone().isoformat(timespec="seconds")
            log.write(f"\n=== {stamp} DC starts ffmpeg (session {session})\n".encode())
            log.flush()
            with self._lock:
                self._session = session
            stream_url = self.params.input if ffmpeg.is_url(self.params.input) else None
            try:
                process = ffmpeg.start(cmd, stream_url)
            except OSError as exc:
                with self._lock:
                    self._session = None
                return "none", f"cannot start {self._executable}: {exc}"
            assert process.stderr is not None
            messages = ffmpeg.ScrubbedLog(process.stderr, log, self._scrubber)
            with self._lock:
                self._process = process
            try:
                code = self._watch(process, messages, session)
            finally:
                ffmpeg.stop(process, messages, self.STOP_GRACE_S)
                with self._lock:
                    self._process = None
                    self._session = None
        return code, messages.last_line

    def _watch(self, process: subprocess.Popen[bytes], messages: ffmpeg.ScrubbedLog, session: str) -> int:
        stall_s = max(self.STALL_MIN_S, 3.0 * self.params.segment_time)
        last_output = time.time()
        while True:
            code = ffmpeg.wait(process, messages, 0.5)
            if code is not None:
                return code
            if self._stopping.is_set():
                return ffmpeg.stop(process, messages, self.STOP_GRACE_S)
            last_output = max(last_output, self._newest_output(session))
            if time.time() - last_output > stall_s:
                # A camera that vanishes without closing the connection leaves ffmpeg waiting forever.
                messages.note(f"=== DC: no output for {stall_s:g} s, stopping ffmpeg\n")
                return ffmpeg.stop(process, messages, self.STOP_GRACE_S)

    def _newest_output(self, session: str) -> float:
        newest = 0.0
        with contextlib.suppress(OSError), os.scandir(self.folder) as entries:
            for entry in entries:
                if entry.name.startswith(session + "_"):
                    with contextlib.suppress(OSError):
                        newest = max(newest, entry.stat().st_mtime)
        return newest

    def _rotate_log(self) -> None:
        with contextlib.suppress(OSError):
            if os.path.getsize(self.log_path) > self.LOG_ROTATE_BYTES:
                os.replace(self.log_path, self.log_path + ".1")

    def _recording(self) -> ffmpeg.Recording:
        p = self.params
        return ffmpeg.Recording(
            input=p.input,
            video=p.video,
            audio=p.audio,
            bitrate_video=p.bitrate_video,
            bitrate_audio=p.bitrate_audio,
            segment=p.segment,
            segment_time=p.segment_time,
            log_level=p.ffmpeg_log_level,
            banner=p.ffmpeg_banner,
        )

    # -- a poll: publish one finished segment --------------------------------------------------

    def collect(self) -> dict[str, Any] | None:
        segments = self._finished_segments()
        self._read_playlists({s.session for s in segments})
        for segment in segments:
            record = self._publish(segment)
            if record is not None:
                return record
        self._tidy()
        return None

    def _finished_segments(self) -> list[_Segment]:
        """The segments ffmpeg is done with, oldest first."""
        with self._lock:
            before = self._session
        found = []
        try:
            names = os.listdir(self.folder)
        except FileNotFoundError:
            return []
        with self._lock:
            after = self._session
        for name in names:
            match = ffmpeg.SEGMENT_NAME.match(name)
            if match is None:
                continue
            unfinished = match["unfinished"] is not None
            # A file not yet renamed is finished only when no ffmpeg writes it any more: left by a
            # previous run (killed server, unsegmented recording that ended).
            if unfinished and match["session"] in (before, after):
                continue
            found.append(_Segment(name, match["session"], int(match["index"]), unfinished))
        found.sort(key=lambda s: (int(s.session), s.index))
        return found

    def _read_playlists(self, sessions: set[str]) -> None:
        for session in sessions:
            try:
                with open(os.path.join(self.folder, f"{session}.m3u8")) as f:
                    listed = ffmpeg.read_playlist(f.read())
            except OSError:
                continue
            self._listed.update(listed)

    def _publish(self, segment: _Segment) -> dict[str, Any] | None:
        source = os.path.join(self.folder, segment.name)
        try:
            stat = os.stat(source)
        except FileNotFoundError:
            return None
        if stat.st_size == 0:  # ffmpeg ended before the first packet: nothing to keep
            os.unlink(source)
            return None
        listed = self._listed.pop(segment.final_name, ffmpeg.Listed(None, None))
        start_s = listed.start_s if listed.start_s is not None else self._estimated_start(segment, stat.st_mtime)
        p = self.params
        # A segment never overwrites another one (two starting in the same second): -1, -2… is appended.
        locations = self._reserved.reserve(file_locations(self.context.paths, p.save_path, start_s), (".ts",))
        local, remote = locations.with_suffix(".ts")
        try:
            _move(source, local)
        finally:
            self._reserved.release(locations.local)
        self.segments += 1
        record: dict[str, Any] = {
            "local_path": local,
            "remote_path": self._relative_to_base(local, start_s),
            "timestamp": datetime.fromtimestamp(start_s, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            "data_src": self.context.name,
        }
        if remote:
            record["remote_paths"] = remote
        if listed.duration_s is not None:
            record["duration"] = round(listed.duration_s, 3)
        return record

    def _estimated_start(self, segment: _Segment, mtime: float) -> float:
        """A start for a segment no playlist describes (a leftover): its session's start for an
        unsegmented recording, else its write time less one segment."""
        session_start = int(segment.session) / 1000.0
        if not self.params.segment:
            return session_start
        return max(session_start, mtime - self.params.segment_time)

    def _relative_to_base(self, local: str, when_s: float) -> str:
        """``local`` without save_local_base_path: the original's ``remote_path``."""
        paths = self.context.paths
        base = expand_time(paths.save_local_base_path, when_s, paths.zone)
        relative = local[len(base) :] if base and local.startswith(base) else local
        return relative.lstrip("/")

    def _tidy(self) -> None:
        """Remove the playlists of ended sessions none of whose segments is left."""
        with self._lock:
            current = self._session
        try:
            names = os.listdir(self.folder)
        except FileNotFoundError:
            return
        with_segments = {m["session"] for m in map(ffmpeg.SEGMENT_NAME.match, names) if m is not None}
        for name in names:
            session = name.split(".", 1)[0]
            if name.endswith((".m3u8", ".m3u8.tmp")) and session != current and session not in with_segments:
                with contextlib.suppress(OSError):
                    os.unlink(os.path.join(self.folder, name))


def _move(source: str, target: str) -> None:
    """Rename, or copy under a hidden name and rename when ``target`` is on another file system."""
    os.makedirs(os.path.dirname(target) or ".", exist_ok=True)
    try:
        os.replace(source, target)
        return
    except OSError as exc:
        if exc.errno != errno.EXDEV:
            raise
    folder, name = os.path.split(target)
    partial = os.path.join(folder, f".{name}.part")
    try:
        shutil.copyfile(source, partial)
        os.replace(partial, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise
    os.unlink(source)
