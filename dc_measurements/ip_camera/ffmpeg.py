"""What the IpCamera measurement needs to know about ffmpeg: its command line, its file names and
playlists, and how to start it so that it never outlives the process that started it.

Kept apart from the plugin so that each piece can be read (and tested) without a running recorder.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import signal
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import IO
from urllib.parse import urlsplit, urlunsplit

# ffmpeg's -loglevel names, quietest first.
LOG_LEVELS = ("quiet", "panic", "fatal", "error", "warning", "info", "verbose", "debug", "trace")
BITRATE = re.compile(r"^[0-9]+[kKmM]?$")
URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://\S+$")

# Entries kept in an HLS playlist: the plugin reads a segment's start and duration there, so a
# segment must still be listed at the poll after it was finished. 100 segments is far more than
# the polls that can pass in between; the playlist stays a few kB.
PLAYLIST_SIZE = 100

# A segment file: <session>_<index>.ts, where <session> is the ffmpeg start time in epoch ms.
# ".tmp" is the name ffmpeg writes a segment under before renaming it (-hls_flags temp_file);
# ".part" the file of an unsegmented recording, renamed by the plugin once ffmpeg has stopped.
SEGMENT_NAME = re.compile(r"^(?P<session>\d+)_(?P<index>\d+)\.ts(?P<unfinished>\.tmp|\.part)?$")

_PR_SET_PDEATHSIG = 1
# Loaded once here: a child between fork and exec must not load libraries (it may deadlock).
_LIBC = ctypes.CDLL(None, use_errno=True)


@dataclass(frozen=True)
class Recording:
    """What ffmpeg records and how (the plugin's parameters, checked)."""

    input: str
    video: bool
    audio: bool
    bitrate_video: str
    bitrate_audio: str
    segment: bool
    segment_time: int
    log_level: str
    banner: bool


def command(executable: str, rec: Recording, folder: str, session: str) -> list[str]:
    """The ffmpeg command line recording one session into ``folder``.

    The video is encoded again with libx264 (ultrafast) rather than copied: only then does every
    segment start with a keyframe exactly every ``segment_time`` seconds, whatever the camera's
    keyframe interval, and ``bitrate_video`` apply. Audio is AAC at ``bitrate_audio``.
    """
    cmd = [executable, "-nostdin", "-nostats", "-loglevel", rec.log_level]
    if not rec.banner:
        cmd.append("-hide_banner")
    cmd += ["-i", rec.input]
    # "?" : a stream the input lacks is not an error (a camera without a microphone).
    if rec.video:
        cmd += ["-map", "0:v:0?", "-c:v", "libx264", "-preset", "ultrafast", "-pix_fmt", "yuv420p"]
        cmd += ["-b:v", rec.bitrate_video]
        if rec.segment:
            cmd += ["-force_key_frames", f"expr:gte(t,n_forced*{rec.segment_time})"]
    else:
        cmd.append("-vn")
    if rec.audio:
        cmd += ["-map", "0:a:0?", "-c:a", "aac", "-b:a", rec.bitrate_audio]
    else:
        cmd.append("-an")
    if rec.segment:
        cmd += [
            "-f",
            "hls",
            "-hls_time",
            str(rec.segment_time),
            "-hls_list_size",
            str(PLAYLIST_SIZE),
            "-hls_segment_type",
            "mpegts",
            # temp_file: a segment gets its .ts name only once complete; program_date_time: its
            # wall-clock start is in the playlist.
            "-hls_flags",
            "temp_file+program_date_time",
            "-hls_segment_filename",
            os.path.join(folder, f"{session}_%05d.ts"),
            os.path.join(folder, f"{session}.m3u8"),
        ]
    else:
        cmd += ["-f", "mpegts", os.path.join(folder, f"{session}_00000.ts.part")]
    return cmd


@dataclass(frozen=True)
class Listed:
    """A segment as its playlist describes it."""

    start_s: float | None
    duration_s: float | None


def read_playlist(text: str) -> dict[str, Listed]:
    """Segment file name → start (epoch s) and duration, from an HLS media playlist."""
    found: dict[str, Listed] = {}
    duration: float | None = None
    start: float | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("#EXTINF:"):
            with contextlib.suppress(ValueError):
                duration = float(line[len("#EXTINF:") :].split(",", 1)[0])
        elif line.startswith("#EXT-X-PROGRAM-DATE-TIME:"):
            start = parse_date_time(line[len("#EXT-X-PROGRAM-DATE-TIME:") :])
        elif line and not line.startswith("#"):
            found[os.path.basename(line)] = Listed(start, duration)
            duration = start = None
    return found


def parse_date_time(text: str) -> float | None:
    """ffmpeg's ``2024-03-01T10:15:42.090+0100`` as epoch seconds."""
    try:
        return datetime.strptime(text.strip(), "%Y-%m-%dT%H:%M:%S.%f%z").timestamp()
    except ValueError:
        return None


def without_password(url: str) -> str:
    """``url`` with the password of its user info masked, for logs."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return url
    if parts.password is None:
        return url
    host = parts.hostname or ""
    if parts.port is not None:
        host = f"{host}:{parts.port}"
    return urlunsplit(parts._replace(netloc=f"{parts.username}:***@{host}"))


def die_with_parent(parent_pid: int) -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGTERM when the thread that started it ends (the process
    killed with -9 included), so ffmpeg is never orphaned. SIGTERM rather than SIGKILL: ffmpeg then
    still writes the segment it holds in memory. Only async-signal-safe calls happen in the child."""

    def setup() -> None:
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:  # the parent died before prctl: nobody would signal us
            os._exit(1)

    return setup


def start(cmd: list[str], log: IO[bytes]) -> subprocess.Popen[bytes]:
    """ffmpeg started with its stderr (and stdout) into ``log``, in its own process group (a
    terminal's Ctrl-C reaches the server, which stops ffmpeg itself, finishing the segment)."""
    return subprocess.Popen(
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=log,
        preexec_fn=die_with_parent(os.getpid()),
        process_group=0,
        close_fds=True,
    )


def stop(process: subprocess.Popen[bytes], grace_s: float) -> int:
    """SIGINT (ffmpeg finishes the segment and the playlist), then SIGKILL after ``grace_s``."""
    if process.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            process.send_signal(signal.SIGINT)
        try:
            process.wait(grace_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            process.wait()
    return process.returncode


def last_lines(path: str, offset: int, count: int = 1) -> list[str]:
    """The last ``count`` non-empty lines written to ``path`` after ``offset``."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(offset, size - 8192))
            data = f.read()
    except OSError:
        return []
    lines = [line.strip() for line in data.decode("utf-8", "replace").splitlines() if line.strip()]
    return lines[-count:]
