"""ffprobe reads a video's duration and nothing else: not a playlist's entries, not a path taken for a URL.

FilesMetrics probes files a record names (confined to its allowed roots first); a file there whose
content is a concat or HLS playlist under a video's name would otherwise make ffprobe open the files
or URLs it lists, with DC's rights.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from dc_core.testing import RecordingLogger
from dc_destinations.files_metrics.media import DurationProbe

if shutil.which("ffmpeg") is None or shutil.which("ffprobe") is None:
    pytest.skip("ffmpeg and ffprobe are not installed (Debian package ffmpeg)", allow_module_level=True)


def video(path: Path, seconds: int) -> Path:
    subprocess.run(
        ["ffmpeg", "-v", "error", "-f", "lavfi", "-i", f"testsrc=duration={seconds}:size=64x48:rate=10",
         "-pix_fmt", "yuv420p", str(path)],
        check=True, timeout=60,
    )  # fmt: skip
    return path


@pytest.mark.parametrize("name", ["clip.mp4", "segment.ts", "clip.mkv", ":colon.mp4", "-dash.mp4"])
def test_a_video_in_an_expected_container_gets_its_duration(tmp_path: Path, name: str) -> None:
    probe = DurationProbe(RecordingLogger())
    assert probe.duration(str(video(tmp_path / name, 1))) == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize(
    "playlist",
    [
        "#EXTM3U\n#EXT-X-TARGETDURATION:3\n#EXTINF:3.0,\nelsewhere.ts\n#EXT-X-ENDLIST\n",
        "ffconcat version 1.0\nfile 'elsewhere.ts'\n",
    ],
    ids=["hls", "concat"],
)
def test_a_playlist_named_as_a_video_is_not_followed(tmp_path: Path, playlist: str) -> None:
    # The listed file is next to it (the demuxers' safe modes allow that): ffprobe without the
    # format allow-list opens it, and reports the HLS playlist's 3 s.
    video(tmp_path / "elsewhere.ts", 3)
    named = tmp_path / "clip.mp4"
    named.write_text(playlist)
    logger = RecordingLogger()
    assert DurationProbe(logger).duration(str(named)) is None
    (warning,) = logger.at("warning")
    assert warning == f"ffprobe found no duration in {named}: file:{named}: Invalid argument"


def test_a_relative_path_is_not_probed(tmp_path: Path) -> None:
    logger = RecordingLogger()
    assert DurationProbe(logger).duration("clip.mp4") is None
    assert logger.at("warning") == ["ffprobe not run on clip.mp4: not an absolute path"]
