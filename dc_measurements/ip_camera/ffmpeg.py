"""What the IpCamera measurement needs to know about ffmpeg: its command line, its file names and
playlists, how to start it so that it never outlives the process that started it, and how to keep
the camera's password out of its command line and its messages.

A stream URL never appears on ffmpeg's command line (where ``ps`` and ``/proc/<pid>/cmdline`` show
it to every local user): ffmpeg 5.1 has no option that takes RTSP credentials other than the URL's
user info, so the URL is given to it in a one-line concat script on its standard input
(``-f concat -i pipe:0``), which no other process can read. ffmpeg's messages name the URL with its
password ("Impossible to open 'rtsp://admin:…@…'"), and at ``-loglevel debug`` the
``Authorization`` header: they are read by DC and written to the log file with every form of the
password masked (:class:`Scrubber`).

Kept apart from the plugin so that each piece can be read (and tested) without a running recorder.
"""

from __future__ import annotations

import base64
import contextlib
import ctypes
import os
import re
import select
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import IO
from urllib.parse import parse_qsl, quote, unquote, urlsplit

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

# Where ffmpeg reads a stream URL: its standard input, as a concat script (see the module's text).
STDIN_INPUT = "pipe:0"
# The protocols a stream may need once the concat script is read (rtsp is a demuxer over tcp, udp,
# rtp, http or tls; hls over http(s)): every network protocol of ffmpeg 5.1, none that reads a
# local file. Without a list concat allows only crypto and data.
NETWORK_PROTOCOLS = (
    "pipe,tcp,udp,udplite,rtp,srtp,tls,http,https,httpproxy,rtmp,rtmps,rtmpt,rtmpts,ffrtmphttp,"
    "mmsh,mmst,hls,srt,rist,sctp,ftp,sftp,crypto,data"
)
# Query parameters that carry credentials in some cameras' URLs (?user=admin&pwd=…, ?token=…).
_SECRET_QUERY_KEY = re.compile(r"pass|pwd|token|secret|key|auth|sig", re.IGNORECASE)
# scheme://user:password@ in any text: the password part is masked even when it is not this
# camera's (a redirect, another URL in a message). The scheme's length is bounded so that a long
# run of letters costs linear time.
_USERINFO = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]{0,31}://[^:/@\s'\"]*):(?P<password>[^@/\s'\"]*)@")
MASK = "***"
# ffmpeg's av_log lines are at most 1 kB; a longer run without a newline is cut there, unscrubbed
# bytes are never written.
MAX_LINE = 64 * 1024
# How long ffmpeg's messages are read after it exited: a process it started could keep its stderr open.
DRAIN_S = 5.0

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
    if is_url(rec.input):
        # The URL comes on stdin (:func:`concat_script`): never on the command line.
        cmd += ["-f", "concat", "-safe", "0", "-protocol_whitelist", NETWORK_PROTOCOLS, "-i", STDIN_INPUT]
    else:
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


def is_url(value: str) -> bool:
    return "://" in value


def concat_script(url: str) -> bytes:
    """The concat script ffmpeg reads on stdin: the one stream to record.

    Inside single quotes nothing is special to ffmpeg's parser but the quote itself, written as
    ``'\\''`` (close, escaped quote, open), as in a shell."""
    quoted = "'" + url.replace("'", "'\\''") + "'"
    return f"ffconcat version 1.0\nfile {quoted}\n".encode()


def without_password(url: str) -> str:
    """``url`` with the password of its user info and its credential-like query values masked, for logs."""
    return Scrubber(url).scrub(url)


def _secret_forms(url: str) -> list[str]:
    """Every way ffmpeg may print the credentials of ``url``: as written, percent-decoded and
    -encoded, and ``user:password`` in base64 (an ``Authorization: Basic`` header at debug level)."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return []
    found: list[str] = []
    username, password = parts.username or "", parts.password
    if password:
        plain = unquote(password)
        found += [password, plain, quote(plain, safe=""), quote(plain)]
        for user, secret in ((username, password), (unquote(username), plain)):
            found.append(base64.b64encode(f"{user}:{secret}".encode()).decode())
    for key, value in parse_qsl(parts.query, keep_blank_values=False):
        if value and _SECRET_QUERY_KEY.search(key):
            found += [value, quote(value, safe=""), quote(value)]
    # Longest first: a form that contains another is masked whole.
    return sorted({form for form in found if form}, key=len, reverse=True)


class Scrubber:
    """Masks the credentials of one stream URL in any text ffmpeg writes.

    Every occurrence of the password (in each form ffmpeg may print it) is masked, wherever it
    appears, and any ``scheme://user:password@`` keeps only its user. A password that is a common
    word masks that word too: safety first, the log stays readable enough. ``pipe:0`` at the start
    of a message is the stream (ffmpeg names its input so): it becomes the masked URL, so that
    "pipe:0: Connection refused" says which camera refused.
    """

    def __init__(self, url: str) -> None:
        self._forms = _secret_forms(url) if is_url(url) else []
        self._input_name = ""
        if is_url(url):
            self._input_name = self.scrub(url)

    def scrub(self, text: str) -> str:
        for form in self._forms:
            text = text.replace(form, MASK)
        text = _USERINFO.sub(lambda m: f"{m['head']}:{MASK}@", text)
        if self._input_name and text.startswith(STDIN_INPUT + ":"):
            text = self._input_name + text[len(STDIN_INPUT) :]
        return text


class ScrubbedLog:
    """ffmpeg's stderr, read by DC and appended to its log file line by line, scrubbed.

    Read from the thread that waits for ffmpeg (:func:`wait`, :func:`stop`), so no other thread
    is needed and ffmpeg never blocks on a full pipe for long; complete lines only are scrubbed
    and written, so a password is never split between two reads.
    """

    def __init__(self, stream: IO[bytes], log: IO[bytes], scrubber: Scrubber) -> None:
        self._fd = stream.fileno()
        os.set_blocking(self._fd, False)
        self._stream = stream
        self._log = log
        self._scrubber = scrubber
        self._pending = b""
        self._cut = False
        self.last_line = ""
        self.closed = False

    def pump(self, timeout: float) -> None:
        """Write what ffmpeg wrote within ``timeout`` seconds (returns early at its end of output)."""
        if self.closed:
            return
        readable, _, _ = select.select([self._fd], [], [], max(timeout, 0.0))
        # At most 1 MB a call: an ffmpeg at -loglevel trace must not keep its supervisor from watching it.
        for _ in range(16 if readable else 0):
            try:
                chunk = os.read(self._fd, 65536)
            except BlockingIOError:
                break
            if not chunk:
                self._end()
                return
            self._take(chunk)
        self._log.flush()

    def drain(self) -> None:
        """Everything up to ffmpeg's end of output (call once it exited), for at most DRAIN_S."""
        deadline = time.monotonic() + DRAIN_S
        while not self.closed and time.monotonic() < deadline:
            self.pump(min(1.0, max(0.0, deadline - time.monotonic())))
        if not self.closed:
            self._end()

    def note(self, text: str) -> None:
        """A line of DC's own in the log (already free of secrets)."""
        self._log.write(text.encode())
        self._log.flush()

    def _take(self, chunk: bytes) -> None:
        if self._cut:  # the rest of a line cut at MAX_LINE is dropped, up to its end
            end = chunk.find(b"\n")
            if end < 0:
                return
            chunk, self._cut = chunk[end + 1 :], False
        *lines, self._pending = (self._pending + chunk).split(b"\n")
        for line in lines:
            self._write(line)
        if len(self._pending) > MAX_LINE:
            self._write(self._pending[:MAX_LINE] + b" [line cut]")
            self._pending, self._cut = b"", True

    def _write(self, raw: bytes) -> None:
        text = self._scrubber.scrub(raw.decode("utf-8", "replace"))
        self._log.write(text.encode() + b"\n")
        if text.strip():
            self.last_line = text.strip()

    def _end(self) -> None:
        if self._pending and not self._cut:
            self._write(self._pending)
        self._pending = b""
        self.closed = True
        self._log.flush()
        with contextlib.suppress(OSError):
            self._stream.close()


def die_with_parent(parent_pid: int) -> Callable[[], None]:
    """A ``preexec_fn``: the child gets SIGTERM when the thread that started it ends (the process
    killed with -9 included), so ffmpeg is never orphaned. SIGTERM rather than SIGKILL: ffmpeg then
    still writes the segment it holds in memory. Only async-signal-safe calls happen in the child."""

    def setup() -> None:
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:  # the parent died before prctl: nobody would signal us
            os._exit(1)

    return setup


def start(cmd: list[str], stream_url: str | None) -> subprocess.Popen[bytes]:
    """ffmpeg started with its stderr on a pipe (for :class:`ScrubbedLog`) and ``stream_url`` as a
    concat script on its stdin, in its own process group (a terminal's Ctrl-C reaches the server,
    which stops ffmpeg itself, finishing the segment). Its segments are made under the server's
    umask (077 in DC's processes)."""
    process = subprocess.Popen(
        cmd,
        stdin=subprocess.PIPE if stream_url is not None else subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        preexec_fn=die_with_parent(os.getpid()),
        process_group=0,
        close_fds=True,
    )
    if process.stdin is not None:
        # A few hundred bytes: the pipe takes them at once, ffmpeg reads them when it opens its input.
        # An ffmpeg that exited first says why on stderr.
        with contextlib.suppress(OSError):
            process.stdin.write(concat_script(stream_url or ""))
        with contextlib.suppress(OSError):
            process.stdin.close()
    return process


def wait(process: subprocess.Popen[bytes], log: ScrubbedLog, timeout: float) -> int | None:
    """ffmpeg's exit code once it exited within ``timeout`` seconds (its messages written), else None."""
    deadline = time.monotonic() + timeout
    while True:
        code = process.poll()
        if code is not None:
            log.drain()
            return code
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        if log.closed:  # stderr closed before the exit: nothing to read, only to wait
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(min(left, 0.5))
        else:
            log.pump(min(left, 0.5))


def stop(process: subprocess.Popen[bytes], log: ScrubbedLog, grace_s: float) -> int:
    """SIGINT (ffmpeg finishes the segment and the playlist), then SIGKILL after ``grace_s``."""
    if process.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            process.send_signal(signal.SIGINT)
        if wait(process, log, grace_s) is None:
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            process.wait()
    log.drain()
    return process.returncode
