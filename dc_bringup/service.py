"""`dc service install PARAMS`: DC as a systemd service, its secrets in an environment file.

The unit runs this environment's dc-bringup on the parameter file, as the user who installs it (the
one whose venv and buffers these are), restarts it when it fails (not when the file is invalid:
exit 2 would fail again at once), and sends its output to the journal, which rotates it; ROS's own
log files are turned off so that nothing else grows without bound. The secrets a parameter file
references as ``${NAME}`` live in the environment file (mode 600), not in the unit, which anyone
may read.
"""

from __future__ import annotations

import argparse
import getpass
import os
import shlex
import sys
from pathlib import Path

UNIT_DIR = Path("/etc/systemd/system")
# dc-bringup's default --stop-timeout is 15 s per server; the servers stop in turn after the manager.
STOP_TIMEOUT_S = 60
INVALID_CONFIGURATION = 2  # dc-bringup's exit code for a file it refuses: restarting cannot mend it


def referenced_variables(params_file: Path) -> list[str]:
    """The environment variables the parameter file references as ``${NAME}``, in name order."""
    from dc_core.config import UnsetShown, load_params

    every_one_unset = UnsetShown({})
    load_params(params_file, environ=every_one_unset)
    return sorted(every_one_unset.unset)


def unit_text(
    params_file: Path, *, name: str, user: str, env_file: Path, bringup: Path, bringup_args: list[str]
) -> str:
    page = Path(__file__).resolve().parent.parent / "docs" / "service.md"
    documentation = f"Documentation=file://{page}\n" if page.is_file() else ""
    command = shlex.join([str(bringup), str(params_file), *bringup_args, "--ros-args", "--disable-external-lib-logs"])
    return f"""\
[Unit]
Description=DC robot data collection ({params_file.name})
{documentation}Wants=network-online.target
After=network-online.target

[Service]
Type=exec
User={user}
# Its home: DC's buffers and run ids live under it, as in the user's own runs.
WorkingDirectory=~
UMask=0077
# Secrets and settings, NAME=value a line (the parameter file's ${{NAME}}, ROS_DOMAIN_ID): mode 600.
EnvironmentFile={env_file}
Environment=PYTHONUNBUFFERED=1 RCUTILS_COLORIZED_OUTPUT=0
ExecStart={command}
# SIGTERM: dc-bringup stops the servers in order, each flushing to its buffer, then exits 0.
KillMode=mixed
TimeoutStopSec={STOP_TIMEOUT_S}
Restart=on-failure
RestartSec=5
RestartPreventExitStatus={INVALID_CONFIGURATION}
StandardOutput=journal
StandardError=journal
SyslogIdentifier={name}
NoNewPrivileges=yes
PrivateTmp=yes
ProtectSystem=full

[Install]
WantedBy=multi-user.target
"""


def env_file_text(params_file: Path, names: list[str]) -> str:
    lines = [
        f"# Environment of DC's service for {params_file}: NAME=value, one a line, no quotes needed.",
        "# Keep this file mode 600: it holds the parameter file's secrets.",
        "# ROS_DOMAIN_ID=0",
    ]
    lines += [f"# {name}=   (referenced as ${{{name}}}: unset, dc-bringup refuses to start)" for name in names]
    return "\n".join(lines) + "\n"


def default_user() -> str:
    # Under sudo, the user who asked: the venv and the buffers under $HOME are theirs.
    return os.environ.get("SUDO_USER") or getpass.getuser()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=["install"], help="install: write the unit (and the environment file)")
    parser.add_argument("params_file")
    parser.add_argument("--name", default="dc", help="the unit's name (default dc: dc.service)")
    parser.add_argument("--user", default="", help="the user it runs as (default: you, or the user sudo was run by)")
    parser.add_argument("--env-file", default="", help="its environment file (default /etc/dc/<name>.env)")
    parser.add_argument("--namespace", default="", help="dc-bringup --namespace")
    parser.add_argument("--unit-dir", default=str(UNIT_DIR), help=f"where the unit is written (default {UNIT_DIR})")
    parser.add_argument("--print", action="store_true", help="print the unit instead of writing anything")


def main(args: argparse.Namespace) -> int:
    from dc_core.errors import DcError

    params_file = Path(args.params_file).resolve()
    try:
        names = referenced_variables(params_file)
    except (DcError, OSError) as exc:
        print(f"dc service: {params_file}: {exc}", file=sys.stderr)
        return 2
    env_file = Path(args.env_file or f"/etc/dc/{args.name}.env").resolve()
    bringup = Path(sys.executable).parent / "dc-bringup"
    extra = ["--namespace", args.namespace] if args.namespace else []
    unit = unit_text(
        params_file,
        name=args.name,
        user=args.user or default_user(),
        env_file=env_file,
        bringup=bringup,
        bringup_args=extra,
    )
    if args.print:
        sys.stdout.write(unit)
        return 0
    unit_path = Path(args.unit_dir) / f"{args.name}.service"
    try:
        unit_path.write_text(unit)
        if not env_file.exists():
            env_file.parent.mkdir(parents=True, exist_ok=True)
            # Made 600 before the first byte: never readable by others, not even for a moment.
            descriptor = os.open(env_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(descriptor, "w") as out:
                out.write(env_file_text(params_file, names))
            print(f"wrote {env_file} (mode 600): set {', '.join(names) or 'nothing yet'} there")
    except OSError as exc:
        print(f"dc service: {exc} (run it with sudo, or --print > a file)", file=sys.stderr)
        return 1
    print(f"wrote {unit_path}")
    print(
        f"next: sudo systemctl daemon-reload && sudo systemctl enable --now {args.name}; journalctl -u {args.name} -f"
    )
    return 0
