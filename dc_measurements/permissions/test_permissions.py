"""Permissions measurement, compared with os.stat and the names of the owner and group."""

from __future__ import annotations

import grp
import os
import pwd
import stat
from pathlib import Path

import pytest

from dc_measurements.permissions import Permissions
from tests.measurement_helpers import assert_valid, configured


@pytest.mark.parametrize(("style", "expected"), [("int", "640"), ("rwx", "rw-r-----")])
def test_permissions_of_a_file(tmp_path: Path, style: str, expected: str) -> None:
    target = tmp_path / "secret"
    target.write_text("x")
    target.chmod(0o640)
    record = configured(Permissions, path=str(target), format=style).collect()
    assert_valid(Permissions, record)
    info = os.stat(target)
    assert record == {
        "exists": True,
        "uid": info.st_uid,
        "gid": info.st_gid,
        "user": pwd.getpwuid(info.st_uid).pw_name,
        "group": record["group"],
        "permissions": expected,
    }
    assert record["group"] == grp.getgrgid(info.st_gid).gr_name


@pytest.mark.parametrize(("style", "expected"), [("int", "1777"), ("rwx", "rwxrwxrwt")])
def test_permissions_show_the_sticky_bit_like_stat_and_ls(tmp_path: Path, style: str, expected: str) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    assert stat.S_IMODE(os.stat(shared).st_mode) == 0o1777
    record = configured(Permissions, path=str(shared), format=style).collect()
    assert_valid(Permissions, record)
    assert record["permissions"] == expected


def test_permissions_of_a_missing_path_says_it_does_not_exist(tmp_path: Path) -> None:
    record = configured(Permissions, path=str(tmp_path / "nothing")).collect()
    assert record == {"exists": False}
    assert_valid(Permissions, record)


def test_permissions_expands_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DC_TEST_PERM", str(tmp_path))
    record = configured(Permissions, path="${DC_TEST_PERM}").collect()
    assert record["exists"] is True
    assert record["permissions"] == f"{stat.S_IMODE(os.stat(tmp_path).st_mode):03o}"
