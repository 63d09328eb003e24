"""What FilesMetrics says about a file's content beyond its type (dc_destinations.content_types): a video's duration."""

from __future__ import annotations

import os
import shutil
import subprocess

from dc_core.logs import Logger

# A video ffprobe cannot read in this time is reported without a duration rather than holding the batch.
PROBE_TIMEOUT_S = 20.0
# The containers of the videos DC records or is given (IpCamera's MPEG-TS, MP4/MOV, Matroska/WebM,
# AVI, FLV, MPEG-PS, Ogg). A file named .mp4 holding a concat or HLS playlist would otherwise make
# ffprobe open the files or URLs it lists.
PROBE_FORMATS = "mpegts,mov,matroska,avi,flv,mpeg,ogg"


def is_video(mime_type: str) -> bool:
    return mime_type.startswith("video/")


class DurationProbe:
    """Seconds of video in a file, read by ffprobe; None when ffprobe is missing or cannot tell."""

    def __init__(self, logger: Logger, ffprobe: str | None = None) -> None:
        self._logger = logger
        self._ffprobe = ffprobe if ffprobe is not None else shutil.which("ffprobe")
        self._missing_told = False

    def duration(self, path: str) -> float | None:
        if not self._ffprobe:
            if not self._missing_told:
                # Once per destination: the rows are still written, with an empty duration.
                self._missing_told = True
                self._logger.warning("ffprobe not found (apt install ffmpeg): videos are recorded without duration")
            return None
        if not os.path.isabs(path):
            # FilesMetrics probes the resolved path of a file it confined to its allowed roots.
            self._logger.warning(f"ffprobe not run on {path}: not an absolute path")
            return None
        # file: — a path is never read as a URL or an option, whatever its first characters.
        command = [
            self._ffprobe,
            "-v",
            "error",
            "-format_whitelist",
            PROBE_FORMATS,
            "-protocol_whitelist",
            "file",
            "-show_entries",
            "format=duration",
            "-of",
            "csv=p=0",
            "file:" + path,
        ]
        try:
            done = subprocess.run(
                command, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL
            )
        except (OSError, subprocess.TimeoutExpired) as exc:
            self._logger.warning(f"ffprobe failed on {path}: {exc}")
            return None
        text = done.stdout.strip()
        try:
            seconds = float(text)
        except ValueError:
            # "N/A" (a stream without a duration) or an unreadable file: not a reason to hold the record.
            problem = done.stderr.strip().splitlines()[-1:] or [text or f"exit status {done.returncode}"]
            self._logger.warning(f"ffprobe found no duration in {path}: {problem[0]}")
            return None
        return seconds if seconds >= 0 else None
