"""An incident's record sent to the MinIO destination: the MCAP file uploaded to a real S3 server (SeaweedFS),
verified, deleted locally, and the stored object readable as the same messages."""

from __future__ import annotations

import io
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy

from dc_bringup.local_servers.seaweedfs import SeaweedS3Server, missing_reason
from dc_core.destination import OutgoingRecord
from dc_core.measurement import BasePaths
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from dc_destinations.minio import MinIO, MinIOParams
from dc_destinations.minio.test_minio import store_settings
from dc_measurements.recorder import Recorder
from tests.destination_helpers import STAMP_NS
from tests.robot_helpers import odometry, ros_session, unique

pytestmark = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    s = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    s.start()
    yield s
    s.stop(timeout=3.0)


def test_an_incident_file_is_uploaded_verified_and_deleted_like_any_saved_file(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    topic = unique("/odom")
    with ros_session("recorder_upload") as ros:
        publisher = ros.node.create_publisher(
            Odometry, topic, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        )
        plugin = ros.harness.make(Recorder, {"topics": [topic], "pre_trigger": 5.0, "post_trigger": 0.0})
        ros.harness.context(plugin).paths = BasePaths(str(tmp_path), "robot1", {"minio": "incidents"})
        plugin.on_configure()
        plugin.on_activate()
        assert ros.spin_until(lambda: publisher.get_subscription_count() == 1)
        for i in range(20):
            publisher.publish(odometry(float(i), 0.0, 0.0))
        assert ros.spin_until(lambda: plugin.counters()["messages"] == 20)
        plugin.trigger("bumper")
        emitted = ros.harness.context(plugin).emitted

        def poll() -> None:
            plugin.on_poll(None)
            ros.harness.run_finished_work(plugin)

        assert ros.spin_until(lambda: bool(emitted), poll)
        ros.harness.stop(plugin)
    record = emitted[0].record
    path = Path(record["local_paths"]["mcap"])
    content = path.read_bytes()

    params = {
        **store_settings(server),
        "src_fields": ["local_paths.mcap"],
        "upload_fields": ["remote_paths.minio.mcap"],
        "allowed_roots": [tempfile.gettempdir()],
        # The Recorder renames a complete file into place: nothing to wait for.
        "complete_after": 0.0,
        "delete_when_sent": True,
    }
    dest = MinIO(FakeContext(name="flb_minio"), parse_params(MinIOParams, params, "destination_server.flb_minio"))
    dest.on_configure()
    dest.on_activate()
    assert dest.send([OutgoingRecord("incident-0", "/dc/measurement/recorder", STAMP_NS, record)]) is None
    assert not path.exists(), "deleted once the store holds it, verified"
    key = record["remote_paths"]["minio"]["mcap"]
    assert key.startswith("robot1/incidents/incidents/")
    stored = bytes(server.client().get_object(Bucket=server.bucket, Key=key)["Body"].read())
    assert stored == content

    from mcap.reader import make_reader

    messages = list(make_reader(io.BytesIO(stored)).iter_messages())
    assert len(messages) == record["messages"] == 20
    dest.on_deactivate()
