"""A record must not choose which file DC uploads and deletes (issue 32, docs/security.md).

The checks alone (confined_files), then the MinIO destination against a real SeaweedFS: a file
outside ``allowed_roots``, a symbolic or hard link from inside to outside, a ``..`` path, a key out
of ``key_prefix``, a file of another user — each refused, counted, given its reason for the dead
letters, and left untouched — while a file inside the root is still uploaded and deleted. Then
destination_server with a publisher that is not one of DC's servers, and the issue's reproduction
through `dc-bringup`. Every refusal test ends with delivered + counted = sent.
"""

from __future__ import annotations

import json
import os
import re
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from dc_bringup.local_servers.seaweedfs import SeaweedS3Server, missing_reason
from dc_core.confined_files import Confinement, FileRefused, check_key, default_roots
from dc_core.destination import OutgoingRecord
from dc_core.errors import ConfigError
from dc_core.handoff import RESEND_TOPIC, frame_key, new_writer_id, resend_qos
from dc_core.lifecycle import ServerLoop
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.minio import MinIO, MinIOParams
from dc_destinations.server import DestinationServer
from dc_interfaces.msg import StringStamped
from tests.bringup_util import Bringup, dc
from tests.destination_helpers import STAMP_NS, forwarding_params

OLD = 10.0
SECRET_CONTENT = b"-----BEGIN OPENSSH PRIVATE KEY-----\nnot a real key\n"


def write(path: Path, content: bytes, mode: int = 0o644) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(content)
    path.chmod(mode)
    then = time.time() - OLD
    os.utime(path, (then, then))
    return path


def fingerprint(path: Path) -> tuple[bytes, int, int]:
    status = path.stat()
    return path.read_bytes(), status.st_mtime_ns, status.st_mode


# -- the checks alone ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "key",
    ["../loot/id_rsa", "a/../../b", "a//b", "a/./b", "a\\..\\b", "", "a/", "a/\x00b", "a/\nb"],
)
def test_a_key_that_could_escape_is_refused(key: str) -> None:
    with pytest.raises(FileRefused):
        check_key(key, "")


def test_a_key_outside_the_prefix_is_refused_inside_accepted() -> None:
    assert check_key("C3PO/2026/map/a.pgm", "C3PO/") == "C3PO/2026/map/a.pgm"
    with pytest.raises(FileRefused, match="not under key_prefix 'C3PO/'"):
        check_key("R2D2/map/a.pgm", "C3PO/")


def test_a_dotdot_path_leaving_the_root_is_refused(tmp_path: Path) -> None:
    root = tmp_path / "data"
    root.mkdir()
    write(tmp_path / "outside.txt", b"x")
    confinement = Confinement([str(root)])
    with pytest.raises(FileRefused, match="outside allowed_roots"):
        confinement.open(f"{root}/../outside.txt")
    assert confinement.check_path(f"{root}/sub/../a.pgm") == str(root / "a.pgm"), "a '..' staying inside is fine"
    assert confinement.open(str(root / "missing.pgm")) is None, "a missing file inside the root: nothing to open"


def test_the_default_root_is_the_measurement_servers_save_folder_before_its_first_strftime(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    assert default_roots(None) == [str(tmp_path / "home" / "ros2" / "data")], "its default: $HOME/ros2/data/%Y/…"
    assert default_roots({"save_local_base_path": "var/dc/data/"}) == [str(tmp_path / "var" / "dc" / "data")]
    section = {"save_local_base_path": "${HOME}/=robot/%Y/%m", "robot": "C3PO"}
    assert default_roots(section) == [str(tmp_path / "home" / "C3PO")]
    with pytest.raises(ConfigError, match=r"measurement_server\.save_local_base_path: .* set allowed_roots"):
        default_roots({"save_local_base_path": "/%Y/%m"})


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"allowed_roots": ["/"]}, 'allowed_roots: expected a list of the folders DC saves files in: "/"'),
        ({"allowed_roots": [""]}, "allowed_roots: expected a list of folders"),
        ({"key_prefix": "../x/"}, "key_prefix: expected an object key prefix"),
    ],
)
def test_configuration_errors_name_the_key(body: dict[str, Any], message: str) -> None:
    settings = {"src_fields": ["local_paths.pgm"], "upload_fields": ["remote_paths.minio.pgm"], **body}
    with pytest.raises(ConfigError) as caught:
        parse_params(MinIOParams, settings, "destination_server.flb_minio")
    assert message in str(caught.value)


# -- the MinIO destination against a real store -----------------------------------------------------------

needs_store = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    if missing_reason() is not None:
        pytest.skip(str(missing_reason()))
    s = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    s.start()
    yield s
    s.stop(timeout=3.0)


def minio(server: SeaweedS3Server, root: Path, logger: RecordingLogger | None = None, **params: Any) -> MinIO:
    s = server.settings()
    settings = {
        "endpoint": f"127.0.0.1:{server.port}",
        "use_ssl": False,
        "access_key_id": s["aws_access_key_id"],
        "secret_access_key": s["aws_secret_access_key"],
        "bucket": s["bucket"],
        "src_fields": ["local_paths.pgm"],
        "upload_fields": ["remote_paths.minio.pgm"],
        "allowed_roots": [str(root)],
        "delete_when_sent": True,
        **params,
    }
    plugin = MinIO(
        FakeContext(name="flb_minio", logger=logger or RecordingLogger()),
        parse_params(MinIOParams, settings, "destination_server.flb_minio"),
    )
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def naming(path: Path | str, key: str, n: int = 0) -> OutgoingRecord:
    data = {"name": "map", "local_paths": {"pgm": str(path)}, "remote_paths": {"minio": {"pgm": key}}}
    return OutgoingRecord(f"r{n}", "/dc/measurement/map", STAMP_NS, data)


def sent_refused(dest: MinIO, batch: list[OutgoingRecord]) -> tuple[set[int], dict[int, str]]:
    """The records confirmed and those rejected (dead letters) of one send; nothing may be left to retry."""
    outcome = dest.send(batch)
    rejected = dict(outcome.reject) if outcome else {}
    assert not (outcome and outcome.retry), outcome
    return set(range(len(batch))) - set(rejected), rejected


@needs_store
def test_the_issues_reproduction_a_private_file_outside_the_roots_is_refused_and_untouched(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    root = tmp_path / "data"
    root.mkdir()
    secret = write(tmp_path / "home" / ".ssh" / "id_rsa", SECRET_CONTENT, 0o600)
    before = fingerprint(secret)
    inside = write(root / "map.pgm", b"P5 the map")
    logger = RecordingLogger("test_confinement.repro")
    dest = minio(server, root, logger)
    batch = [naming(secret, "loot/id_rsa", 0), naming(inside, "repro/map.pgm", 1)]

    delivered, refused = sent_refused(dest, batch)

    assert refused[0] == f"refused: {secret} is outside allowed_roots ({root}) (local_paths.pgm)"
    assert fingerprint(secret) == before, "content, mtime and mode untouched"
    assert server.objects("loot/") == {}
    assert delivered == {1} and not inside.exists(), "the file inside the root: uploaded and deleted as before"
    assert server.objects("repro/") == {"repro/map.pgm": b"P5 the map"}
    counters = dest.counters()
    assert counters["files_refused"] == 1 and counters["files_uploaded"] == 1 and counters["files_deleted"] == 1
    assert len(delivered) + counters["files_refused"] == len(batch)
    assert logger.at("warning") == [
        f"destination flb_minio: files or keys named by records refused: 1 ({refused[0]})"
    ], "logged once"


@needs_store
def test_links_and_dotdot_from_inside_the_root_to_outside_are_refused(server: SeaweedS3Server, tmp_path: Path) -> None:
    root = tmp_path / "data"
    root.mkdir()
    outside = write(tmp_path / "outside" / "shadow", SECRET_CONTENT, 0o600)
    before = fingerprint(outside)
    (root / "link.pgm").symlink_to(outside)
    os.link(outside, root / "hard.pgm")
    (root / "folder").symlink_to(outside.parent)  # a folder link: the path looks inside, the file is not
    logger = RecordingLogger("test_confinement.links")
    dest = minio(server, root, logger)
    batch = [
        naming(root / "link.pgm", "links/symlink", 0),
        naming(root / "hard.pgm", "links/hardlink", 1),
        naming(f"{root}/../outside/shadow", "links/dotdot", 2),
        naming(root / "folder" / "shadow", "links/folder", 3),
    ]

    delivered, refused = sent_refused(dest, batch)

    assert delivered == set()
    assert refused[0].startswith(f"refused: {root / 'link.pgm'} is outside allowed_roots")
    assert refused[1] == (
        f"refused: {root / 'hard.pgm'} has 2 hard links: it may be a file from elsewhere (local_paths.pgm)"
    )
    assert refused[2].startswith(f"refused: {root}/../outside/shadow is outside allowed_roots")
    assert refused[3].startswith(f"refused: {root / 'folder' / 'shadow'} is outside allowed_roots")
    assert fingerprint(outside) == before
    assert (root / "link.pgm").is_symlink() and (root / "hard.pgm").exists(), "nothing named by them deleted"
    assert server.objects("links/") == {}
    assert dest.counters()["files_refused"] == len(batch)
    assert len(delivered) + dest.counters()["files_refused"] == len(batch)
    assert len(logger.at("warning")) == 1, "one line for the burst"


@needs_store
def test_keys_out_of_the_prefix_or_with_dotdot_are_refused_and_the_file_kept(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    root = tmp_path / "data"
    files = [write(root / f"m{i}.pgm", f"P5 {i}".encode()) for i in range(4)]
    dest = minio(server, root, key_prefix="C3PO/")
    batch = [
        naming(files[0], "R2D2/m0.pgm", 0),
        naming(files[1], "C3PO/../R2D2/m1.pgm", 1),
        naming(files[2], "C3PO//m2.pgm", 2),
        naming(files[3], "C3PO/map/m3.pgm", 3),
    ]

    delivered, refused = sent_refused(dest, batch)

    assert refused[0] == "refused: object key 'R2D2/m0.pgm' is not under key_prefix 'C3PO/' (local_paths.pgm)"
    assert "'..' segment" in refused[1] and "empty" in refused[2]
    assert delivered == {3}
    assert [f.exists() for f in files] == [True, True, True, False], "only the accepted one was deleted"
    assert set(server.objects("")) >= {"C3PO/map/m3.pgm"}
    assert not {"R2D2/m0.pgm", "R2D2/m1.pgm"} & set(server.objects("R2D2/"))
    assert len(delivered) + dest.counters()["files_refused"] == len(batch)


@needs_store
@pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")
def test_a_file_of_another_user_inside_the_root_is_refused(server: SeaweedS3Server, tmp_path: Path) -> None:
    root = tmp_path / "data"
    theirs = write(root / "theirs.pgm", b"P5 theirs")
    os.chown(theirs, 65534, 65534)
    before = fingerprint(theirs)
    dest = minio(server, root)
    delivered, refused = sent_refused(dest, [naming(theirs, "owner/theirs.pgm")])
    assert refused[0] == f"refused: {theirs} is owned by uid 65534, not by DC's user (uid 0) (local_paths.pgm)"
    assert fingerprint(theirs) == before and server.objects("owner/") == {}
    assert len(delivered) + dest.counters()["files_refused"] == 1


@needs_store
def test_a_file_replaced_after_the_upload_is_not_deleted(
    server: SeaweedS3Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "data"
    path = write(root / "swap.pgm", b"P5 uploaded")
    dest = minio(server, root)
    upload = dest._upload

    def upload_then_swap(opened: Any, key: str, metadata: dict[str, str]) -> int:
        size = upload(opened, key, metadata)
        # Another file takes the name once the upload is done: the one verified is not it.
        os.replace(write(root / "other.tmp", b"P5 someone else's"), path)
        return size

    monkeypatch.setattr(dest, "_upload", upload_then_swap)
    assert dest.send([naming(path, "swap/swap.pgm")]) is None
    assert path.read_bytes() == b"P5 someone else's", "the name now holds another file: left alone"
    assert server.objects("swap/") == {"swap/swap.pgm": b"P5 uploaded"}
    assert dest.counters()["files_deleted"] == 0


# -- records from publishers that are not DC's own servers -----------------------------------------------


def server_params(tmp_path: Path, server: SeaweedS3Server, topic: str, root: Path) -> Path:
    s = server.settings()
    document = {
        "destination_server": {
            "ros__parameters": {
                "flb": {"storage_path": str(tmp_path / "buffer"), "flush": 0.05, "grace": 2.0},
                "destination_plugins": ["disk", "flb_minio"],
                "disk": {
                    "plugin": "dc_destinations/File",
                    "inputs": [topic],
                    "path": str(tmp_path / "out"),
                    "file": "records.jsonl",
                },
                "flb_minio": {
                    "plugin": "dc_destinations/MinIO",
                    "inputs": [topic],
                    "endpoint": f"127.0.0.1:{server.port}",
                    "use_ssl": False,
                    "access_key_id": s["aws_access_key_id"],
                    "secret_access_key": s["aws_secret_access_key"],
                    "bucket": s["bucket"],
                    "src_fields": ["local_paths.pgm"],
                    "upload_fields": ["remote_paths.minio.pgm"],
                    "allowed_roots": [str(root)],
                    "complete_after": 0.0,
                },
            }
        }
    }
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(document, sort_keys=False))
    return params


def run_server_with_publisher(
    tmp_path: Path, server: SeaweedS3Server, node_name: str, records: int, *, as_resent: bool = False
) -> tuple[DestinationServer, Path, list[Path], str]:
    """destination_server in this process, and a publisher node ``node_name`` in a second context (another
    process' node, as far as DDS is concerned) publishing ``records`` records tagged for both destinations,
    each naming a file inside the root. Returns once the server handled them all.

    ``as_resent``: the topic is one DC's measurement server publishes, and the records come on the
    hand-off's resend topic as if sent again by that server (dc_core.handoff)."""
    name = f"map_{uuid.uuid4().hex[:8]}"
    topic = f"/dc/measurement/{name}"
    root = tmp_path / "data"
    files = [write(root / f"map-{i}.pgm", f"P5 {i}".encode()) for i in range(records)]
    params = server_params(tmp_path, server, topic, root)
    if as_resent:
        document = yaml.safe_load(params.read_text())
        document["measurement_server"] = {
            "ros__parameters": {"measurement_plugins": [name], name: {"plugin": "dc_measurements/Uptime"}}
        }
        params.write_text(yaml.safe_dump(document, sort_keys=False))
    rclpy.init()
    publisher_context = Context()
    rclpy.init(context=publisher_context)
    try:
        dest = DestinationServer(str(params))
        executor = SingleThreadedExecutor()
        executor.add_node(dest)
        node = rclpy.create_node(node_name, context=publisher_context)
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
        # Resent: nothing but DC's servers would publish on the topic itself (here, nobody does).
        publisher = (
            node.create_publisher(StringStamped, "/" + RESEND_TOPIC, resend_qos())
            if as_resent
            else node.create_publisher(StringStamped, topic, qos)
        )
        loop = ServerLoop(executor, dest.intake)
        try:
            assert dest.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert dest.trigger_activate() == TransitionCallbackReturn.SUCCESS
            deadline = time.monotonic() + 15
            while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
                loop.spin_once(timeout_sec=0.02)
            prefix = uuid.uuid4().hex[:8]
            writer = new_writer_id()
            for i, path in enumerate(files):
                msg = StringStamped()
                if as_resent:
                    msg.header.frame_id = f"{frame_key(writer, i + 1, 1)}@{topic}"
                msg.data = json.dumps({
                    "tags": ["disk", "flb_minio"],
                    "local_paths": {"pgm": str(path)},
                    "remote_paths": {"minio": {"pgm": f"{prefix}/map-{i}.pgm"}},
                })  # fmt: skip
                publisher.publish(msg)
            while dest.stats.received < records and time.monotonic() < deadline:
                loop.spin_once(timeout_sec=0.02)
            assert dest.stats.received == records
            assert dest.pipeline is not None and dest.pipeline.flush_intake(10)
            # The uploads (if any) run in the sender's thread: wait for it to have had the records.
            while time.monotonic() < deadline:
                minio = dest.pipeline.metrics()["flb_minio"]
                if minio["sent"] + minio["dead_lettered"] + sum(dest.stats.untrusted_tags.values()) >= records:
                    break
                loop.spin_once(timeout_sec=0.05)
            return dest, root, files, prefix
        finally:
            if dest.lifecycle_state in ("active", "inactive"):
                dest.trigger_shutdown()
            executor.shutdown()
            dest.destroy_node()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=publisher_context)
        rclpy.shutdown()


@needs_store
def test_a_record_from_a_publisher_that_is_not_dc_does_not_reach_a_file_destination_by_its_tags(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    dest, _, files, prefix = run_server_with_publisher(tmp_path, server, "dc_test_outsider", 3)
    topic = next(iter(dest.stats.untrusted_tags))[0] if dest.stats.untrusted_tags else ""
    assert dest.stats.untrusted_tags == {(topic, "flb_minio"): 3}
    assert dest.intake_metrics()["untrusted_tags"] == {topic: {"flb_minio": 3}}
    assert all(f.exists() for f in files) and server.objects(f"{prefix}/") == {}
    lines = (tmp_path / "out" / "records.jsonl").read_text().splitlines()
    assert len(lines) == 3, "the destinations that read no file still get the records"
    delivered = len(server.objects(f"{prefix}/"))
    assert delivered + sum(dest.stats.untrusted_tags.values()) == len(files)


@needs_store
def test_a_record_from_a_node_named_measurement_server_reaches_it__the_graph_trusts_names(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    # Without SROS2 a node's name is its own claim (docs/security.md): this is what the check is,
    # and what the allowed_roots and ownership checks are there for.
    dest, _, files, prefix = run_server_with_publisher(tmp_path, server, "measurement_server", 2)
    assert not dest.stats.untrusted_tags
    assert len(server.objects(f"{prefix}/")) == 2
    assert all(f.exists() for f in files), "delete_when_sent is false by default"


@needs_store
def test_records_on_the_resend_topic_from_a_publisher_that_is_not_dc_do_not_reach_a_file_destination(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    # The hand-off's resend topic speaks for DC's own topics: an outsider publishing there must not get
    # the trust DC's servers have on the topic its records name.
    dest, _, files, prefix = run_server_with_publisher(tmp_path, server, "dc_test_outsider", 3, as_resent=True)
    assert sum(dest.stats.untrusted_tags.values()) == 3, dest.stats.untrusted_tags
    assert all(f.exists() for f in files) and server.objects(f"{prefix}/") == {}
    lines = (tmp_path / "out" / "records.jsonl").read_text().splitlines()
    assert len(lines) == 3, "the destinations that read no file still get the records"
    assert len(server.objects(f"{prefix}/")) + sum(dest.stats.untrusted_tags.values()) == len(files)


# -- the issue's reproduction through dc-bringup ------------------------------------------------------------


def status(run: Bringup) -> dict[str, Any]:
    line = run.wait_stderr("destination_server]: metrics HTTP server on http://")
    match = re.search(r"http://[^:/]+:(\d+)/", line)
    assert match, line
    result = dc("status", "--json", "--port", match.group(1), env=run.env)
    assert result.returncode == 0, result.stderr
    document: dict[str, Any] = json.loads(result.stdout)
    return document


@needs_store
@pytest.mark.e2e
def test_e2e_the_issues_dc_pub_is_refused_and_dc_s_own_files_still_go(server: SeaweedS3Server, tmp_path: Path) -> None:
    s = server.settings()
    settings = {
        "plugin": "dc_destinations/MinIO",
        "endpoint": f"127.0.0.1:{server.port}",
        "use_ssl": False,
        "access_key_id": s["aws_access_key_id"],
        "secret_access_key": s["aws_secret_access_key"],
        "bucket": s["bucket"],
        "src_fields": ["local_paths.pgm"],
        "upload_fields": ["remote_paths.minio.pgm"],
        "complete_after": 0.2,
        "delete_when_sent": True,
    }
    params = forwarding_params(tmp_path, "flb_minio", settings, measurement="map", topic="/map-files")
    document = yaml.safe_load(params.read_text())
    document["destination_server"]["ros__parameters"]["flb"].update(http_server=True, http_port=0)
    params.write_text(yaml.safe_dump(document, sort_keys=False))
    home = tmp_path / "home"
    saved = write(home / "ros2" / "data" / "2026" / "map.pgm", b"P5 a map DC saved")  # the default root
    secret = write(home / ".ssh" / "id_rsa", SECRET_CONTENT, 0o600)
    before = fingerprint(secret)
    prefix = uuid.uuid4().hex[:8]

    def record(path: Path, key: str, tags: bool) -> str:
        body: dict[str, Any] = {"local_paths": {"pgm": str(path)}, "remote_paths": {"minio": {"pgm": key}}}
        return json.dumps({"tags": ["flb_minio"], **body} if tags else body)

    with Bringup(params, home) as run:
        run.wait_ready()
        # Through DC's own measurement (a forwarding StringStamped): the file outside the roots is
        # refused, the one DC saved is uploaded and deleted.
        for body in (record(secret, "loot/id_rsa", False), record(saved, f"{prefix}/map.pgm", False)):
            assert dc("pub", "/map-files", body, env=run.env).returncode == 0
        run.wait_until(lambda: not saved.exists(), 30, "DC's own file uploaded and deleted")
        run.wait_until(lambda: status(run)["destinations"]["flb_minio"]["dead_lettered"] == 1, 30, "a dead letter")
        # The issue's command: straight onto DC's topic, routing itself by tags.
        again = write(home / "ros2" / "data" / "2026" / "other.pgm", b"P5 another")
        result = dc("pub", "/dc/measurement/map", record(again, "loot/other", True), env=run.env)
        assert result.returncode == 0, result.stderr
        run.wait_until(
            lambda: status(run)["intake"]["untrusted_tags"].get("/dc/measurement/map") == {"flb_minio": 1},
            30,
            "the outside publisher's record counted",
        )
        final = status(run)
    letters = dc("buffer", "list", "--json", "--params", str(params), env=run.env, timeout=30)
    assert letters.returncode == 0, letters.stderr
    (letter,) = [json.loads(line) for line in letters.stdout.splitlines() if line.strip()]
    assert f"refused: {secret} is outside allowed_roots" in json.dumps(letter), letter
    minio = final["destinations"]["flb_minio"]
    assert minio["plugin"]["files_refused"] == 1
    assert fingerprint(secret) == before
    assert again.read_bytes() == b"P5 another"
    assert server.objects("loot/") == {}
    assert server.objects(f"{prefix}/") == {f"{prefix}/map.pgm": b"P5 a map DC saved"}
    sent = 3
    assert (
        minio["sent"] + minio["dead_lettered"] + final["intake"]["untrusted_tags"]["/dc/measurement/map"]["flb_minio"]
        == sent
    )
