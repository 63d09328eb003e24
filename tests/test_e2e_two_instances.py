"""Two DC instances on one machine: each delivers its own records, or the second refuses to start.

The reported case: two dc-bringup runs (different ROS domains, different output folders, a File
destination named `out` in both, the default buffer location) shared one buffer, and each
delivered some of the other's records, silently. Both instances here share $HOME, as two runs
of one user do.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.bringup_util import Bringup, dc

pytestmark = pytest.mark.e2e

RECORDS = 50


def write_params(folder: Path, storage_path: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    flb = f'    flb:\n      storage_path: "{storage_path}"\n' if storage_path else ""
    params = folder / "params.yaml"
    params.write_text(
        f"""destination_server:
  ros__parameters:
{flb}    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/File"
      inputs: ["/direct"]
      path: "{folder / "out"}"
      file: "records.jsonl"
"""
    )
    return params


def lines(folder: Path) -> list[dict[str, str]]:
    path = folder / "out" / "records.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_two_instances_with_the_default_buffer_each_deliver_exactly_their_own_records(tmp_path: Path) -> None:
    home = tmp_path / "home"
    with (
        Bringup(write_params(tmp_path / "a"), home) as a,
        Bringup(write_params(tmp_path / "b"), home) as b,
    ):
        for run, name in ((a, "a"), (b, "b")):
            run.wait_ready()
            published = dc(
                "pub", "/direct", json.dumps({"src": name, "tags": ["out"]}), "--count", str(RECORDS), "--rate", "100",
                env=run.env,
            )  # fmt: skip
            assert published.returncode == 0, published.stderr
        for run, name in ((a, "a"), (b, "b")):

            def delivered(folder: Path = tmp_path / name) -> bool:
                return len(lines(folder)) >= RECORDS

            run.wait_until(delivered, 30, f"{name}'s records")
    for name in ("a", "b"):
        sources = [line["src"] for line in lines(tmp_path / name)]
        assert sources == [name] * RECORDS, f"{name} delivered {sources.count('a')} of a's, {sources.count('b')} of b's"
    buffers = sorted(p.relative_to(home) for p in home.rglob("delivery.sqlite3"))
    assert buffers == sorted(
        Path(".local/share/dc/buffer") / f"domain-{run.domain_id}" / "default" / "delivery.sqlite3" for run in (a, b)
    )


def test_a_second_instance_on_the_same_buffer_refuses_to_start_and_names_the_owner(tmp_path: Path) -> None:
    home = tmp_path / "home"
    shared = str(tmp_path / "shared-buffer")
    with Bringup(write_params(tmp_path / "a", shared), home) as a:
        a.wait_ready()
        (owner,) = [
            m.group(1) for line in a.stderr if (m := re.search(r"destination_server active \(pid (\d+)\)", line))
        ]
        with Bringup(write_params(tmp_path / "b", shared), home) as b:
            assert b.wait_exit(60) != 0
        refusal = "\n".join(b.stderr)
        assert f"the delivery buffer {shared}/delivery.sqlite3 is in use by process {owner}" in refusal, refusal
        assert "destination_server.ros__parameters.flb.storage_path" in refusal
        # The first instance is not disturbed.
        published = dc("pub", "/direct", '{"src": "a", "tags": ["out"]}', "--count", "3", "--rate", "50", env=a.env)
        assert published.returncode == 0, published.stderr
        a.wait_until(lambda: len(lines(tmp_path / "a")) >= 3, 30, "a's records")
    assert lines(tmp_path / "b") == []
