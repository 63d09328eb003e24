"""Permissions measurement: owner, group, existence and mode of a file or directory."""

from __future__ import annotations

import grp
import os
import pwd
import stat
from dataclasses import dataclass
from typing import Any

from dc_core.errors import ConfigError, PluginError
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param
from dc_core.paths import expand_env


@dataclass(frozen=True, kw_only=True)
class PermissionsParams:
    path: str = param(doc="File or directory to inspect ($ENV expanded)")
    format: str = param("int", choices=("int", "rwx"), doc='"int" for "640", "rwx" for "rw-r-----"')


def user_name(uid: int) -> str | None:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return None


def group_name(gid: int) -> str | None:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return None


def format_mode(mode: int, style: str) -> str:
    """Permission bits as `ls -l` shows them ("rw-r-----") or as `stat -c %a` ("640", "1777")."""
    if style == "rwx":
        return stat.filemode(mode)[1:]
    return f"{stat.S_IMODE(mode):03o}"


class Permissions(Measurement[PermissionsParams]):
    """Owner, group, existence and permissions (octal or rwx) of a file or directory."""

    def __init__(self, context: MeasurementContext, params: PermissionsParams) -> None:
        super().__init__(context, params)
        self.path = ""

    def on_configure(self) -> None:
        try:
            self.path = expand_env(self.params.path)
        except ConfigError as exc:
            raise PluginError(f"{self.context.name}: path: {exc.message}") from exc

    def collect(self) -> dict[str, Any]:
        try:
            info = os.stat(self.path)
        except OSError:
            # Whether the path exists is itself the measurement (e.g. a mount that went away).
            return {"exists": False}
        return {
            "exists": True,
            "uid": info.st_uid,
            "gid": info.st_gid,
            "user": user_name(info.st_uid),
            "group": group_name(info.st_gid),
            "permissions": format_mode(info.st_mode, self.params.format),
        }
