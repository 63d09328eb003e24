"""The delivery buffer's files are the user's alone (0700 folder, 0600 files) whatever the umask of
whoever started DC; what an older DC left open is tightened; a folder DC did not create is left alone.

(A whole run under dc-bringup, the processes' umask included: tests/test_e2e_secrets.py.)
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from dc_core.private_files import make_folders, mode_problem, parse_mode, tighten
from dc_core.testing import RecordingLogger
from dc_destinations.buffer import FILE_NAME, PendingRecord, SqliteBuffer
from dc_destinations.settings import DeliveryParams
from dc_destinations.storage import BufferLock, storage_dir


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture
def open_umask() -> Iterator[None]:
    """A process started with the usual 022: what DC's own modes must not depend on."""
    previous = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(previous)


@pytest.mark.usefixtures("open_umask")
def test_a_new_buffer_is_a_0700_folder_of_0600_files(tmp_path: Path) -> None:
    folder = storage_dir(DeliveryParams(storage_path=str(tmp_path / "new" / "buffer")), RecordingLogger())
    assert mode(folder) == mode(folder.parent) == 0o700
    lock = BufferLock(folder / FILE_NAME)
    lock.acquire()
    buffer = SqliteBuffer(folder / FILE_NAME)
    try:
        buffer.append({"dest": [PendingRecord(record_id="r", topic="/t", stamp_ns=1, payload='{"x":"private"}')]})
        buffer.dead_letter("dest", [(row, "refused") for row in buffer.read_batch("dest", 10)])
        names = {path.name: mode(path) for path in folder.iterdir()}
    finally:
        buffer.close()
        lock.release()
    assert {f"{FILE_NAME}-wal", f"{FILE_NAME}-shm", f"{FILE_NAME}.lock"} <= set(names)
    assert set(names.values()) == {0o600}, names


@pytest.mark.usefixtures("open_umask")
def test_an_older_dcs_open_buffer_files_are_tightened_its_folder_left_with_a_warning(tmp_path: Path) -> None:
    folder = tmp_path / "shared"
    folder.mkdir(mode=0o755)
    folder.chmod(0o755)
    SqliteBuffer(folder / FILE_NAME).close()
    for path in folder.iterdir():
        path.chmod(0o644)
    (folder / f"{FILE_NAME}.lock").write_text("")
    (folder / f"{FILE_NAME}.lock").chmod(0o644)
    logger = RecordingLogger()
    assert storage_dir(DeliveryParams(storage_path=str(folder)), logger) == folder
    lock = BufferLock(folder / FILE_NAME)
    lock.acquire()
    SqliteBuffer(folder / FILE_NAME).close()
    lock.release()
    assert {path.name: mode(path) for path in folder.iterdir()} == {
        FILE_NAME: 0o600,
        f"{FILE_NAME}.lock": 0o600,
    }
    # It may be /tmp or a team's folder: not DC's to change, but said.
    assert mode(folder) == 0o755
    (warning,) = logger.at("warning")
    assert str(folder) in warning and "mode 755" in warning and "chmod 700" in warning


def test_a_link_in_place_of_a_file_dc_owns_is_not_followed(tmp_path: Path) -> None:
    target = tmp_path / "elsewhere"
    target.write_text("someone's")
    target.chmod(0o644)
    (tmp_path / "buffer").mkdir()
    link = tmp_path / "buffer" / f"{FILE_NAME}.lock"
    link.symlink_to(target)
    tighten(link)
    assert mode(target) == 0o644
    with pytest.raises(OSError):
        BufferLock(tmp_path / "buffer" / FILE_NAME).acquire()
    assert mode(target) == 0o644 and target.read_text() == "someone's"


@pytest.mark.usefixtures("open_umask")
def test_folders_are_made_with_exactly_their_mode_and_existing_ones_kept(tmp_path: Path) -> None:
    (tmp_path / "kept").mkdir(mode=0o755)
    make_folders(tmp_path / "kept" / "a" / "b", 0o750)
    assert mode(tmp_path / "kept") == 0o755
    assert mode(tmp_path / "kept" / "a") == mode(tmp_path / "kept" / "a" / "b") == 0o750


@pytest.mark.parametrize(
    ("value", "expected"),
    [("0600", 0o600), ("640", 0o640), ("0o644", 0o644), (" 0600 ", 0o600)],
)
def test_a_mode_is_a_quoted_octal_string(value: str, expected: int) -> None:
    assert mode_problem(value) is None
    assert parse_mode(value) == expected


@pytest.mark.parametrize("value", [416, 640, "0800", "rw-r-----", "01777", ""])
def test_a_mode_that_is_not_a_quoted_octal_string_of_permission_bits_is_refused(value: object) -> None:
    assert mode_problem(value) is not None


def test_a_file_where_a_folder_is_wanted_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "taken").write_text("")
    with pytest.raises(NotADirectoryError):
        make_folders(tmp_path / "taken")
    with pytest.raises(NotADirectoryError):
        make_folders(tmp_path / "taken" / "below")
