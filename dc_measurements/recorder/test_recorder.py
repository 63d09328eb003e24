"""Recorder: the ring and its bound, windows and triggers, and an MCAP file of real DDS traffic read back."""

from __future__ import annotations

import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

from dc_core.measurement import BasePaths
from dc_measurements.recorder import Recorder
from dc_measurements.recorder.ring import ENTRY_OVERHEAD, Ring
from dc_measurements.recorder.window import HOUR_NS, Outcome, Windows
from tests.measurement_helpers import assert_valid
from tests.robot_helpers import Ros, odometry, ros_session, tf_message, transform, unique

S = 1_000_000_000
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
VOLATILE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


# -- the ring (no ROS) -----------------------------------------------------------------------------
def test_the_ring_stays_under_its_bound_oldest_first_and_counts_what_it_let_go() -> None:
    size = 1000
    bound = 10 * (size + ENTRY_OVERHEAD)
    ring = Ring(bound, keep_ns=100 * S, topics=2)
    for i in range(50):
        ring.append(i * S, i * S, i % 2, bytes(size))
        assert ring.bytes <= bound
    kept = ring.window(0, 100 * S)
    # The newest ten are kept; the forty older ones were let go, and each is counted on its topic.
    assert [e[0] // S for e in kept] == list(range(40, 50))
    assert ring.lost_to_bound == [20, 20]
    assert len(kept) + sum(ring.lost_to_bound) == 50


def test_the_ring_lets_go_uncounted_what_is_older_than_pre_trigger_unless_a_window_holds_it() -> None:
    ring = Ring(10**9, keep_ns=2 * S, topics=1)
    for i in range(10):
        ring.append(i * S, 0, 0, b"x")
    assert [e[0] // S for e in ring.window(0, 100 * S)] == [7, 8, 9]
    assert ring.lost_to_bound == [0]
    ring.hold_from_ns = 7 * S  # an open window started at 7 s: its messages stay past pre_trigger
    for i in range(10, 15):
        ring.append(i * S, 0, 0, b"x")
    assert [e[0] // S for e in ring.window(7 * S, 100 * S)] == list(range(7, 15))


def test_a_window_cut_by_the_bound_is_counted_in_lost_in_window() -> None:
    ring = Ring(3 * (10 + ENTRY_OVERHEAD), keep_ns=100 * S, topics=1)
    ring.hold_from_ns = 0
    for i in range(5):
        ring.append(i * S, 0, 0, bytes(10))
    assert ring.take_lost_in_window() == [2]
    assert ring.take_lost_in_window() == [0]


def test_what_the_bound_let_go_before_a_window_opened_counts_in_it() -> None:
    ring = Ring(3 * (10 + ENTRY_OVERHEAD), keep_ns=4 * S, topics=2)
    for i in range(6):
        ring.append(i * S, 0, i % 2, bytes(10))
    # Three let go (0, 1 and 2 s), outside any window: a window opening at 1 s lacks two of them.
    assert ring.lost_to_bound == [2, 1] and ring.lost_since(1 * S) == [1, 1]
    ring.append(6 * S, 0, 0, bytes(10))  # 3 s let go; 0 and 1 s are older than keep_ns: no window reaches them
    assert ring.lost_to_bound == [2, 2] and ring.lost_since(0) == [1, 1]


def test_a_window_being_written_counts_in_the_bound_until_it_is_written() -> None:
    size = 1000
    bound = 10 * (size + ENTRY_OVERHEAD)
    ring = Ring(bound, keep_ns=100 * S, topics=1)
    for i in range(10):
        ring.append(i * S, 0, 0, bytes(size))
    window = ring.window(0, 9 * S)
    token = ring.writing(0, 9 * S, window)  # the worker holds the window's ten messages until its file is written
    for i in range(10, 20):
        ring.append(i * S, 0, 0, bytes(size))
        assert ring.bytes + ring.held_out <= bound  # the window's messages are still in memory
    # Nothing new fitted beside the window: each message after it was let go, counted, none of the window's.
    assert len(ring) == 0 and ring.lost_to_bound == [10] and len(window) == 10
    ring.written(token)
    assert ring.held_out == 0
    for i in range(20, 35):
        ring.append(i * S, 0, 0, bytes(size))
    assert [e[0] // S for e in ring.window(0, 100 * S)] == list(range(25, 35))
    # Every message appended: in the file, kept, or counted.
    assert len(window) + len(ring) + sum(ring.lost_to_bound) == 35


def test_latched_messages_come_with_a_window_however_old_dated_at_its_start() -> None:
    ring = Ring(10**9, keep_ns=20 * S, topics=2)
    ring.append(1 * S, 5, 1, b"static", latched=True)
    for i in range(2, 100):
        ring.append(i * S, 0, 0, b"odom")
    window = ring.window(90 * S, 95 * S)
    assert window[0] == (90 * S, 5, 1, b"static")
    assert [e[0] // S for e in window[1:]] == [90, 91, 92, 93, 94, 95]


# -- windows and triggers (no ROS) -----------------------------------------------------------------
def test_a_trigger_inside_a_window_extends_it_and_cooldown_and_the_hourly_limit_are_counted() -> None:
    windows = Windows(pre_ns=2 * S, post_ns=3 * S, cooldown_ns=10 * S, max_per_hour=2)
    assert windows.trigger(100 * S, "a") is Outcome.OPENED
    assert windows.trigger(102 * S, "b") is Outcome.EXTENDED
    assert windows.due(104 * S) is None  # extended to 105
    incident = windows.due(105 * S)
    assert incident is not None
    assert (incident.start_ns, incident.end_ns) == (98 * S, 105 * S)
    assert [t.reason for t in incident.triggers] == ["a", "b"]
    assert windows.trigger(114 * S, "c") is Outcome.COOLDOWN  # cooldown until 115
    assert windows.trigger(115 * S, "d") is Outcome.OPENED
    windows.due(200 * S)
    assert windows.trigger(300 * S, "e") is Outcome.RATE_LIMITED  # two already in this hour
    assert windows.trigger(100 * S + HOUR_NS, "f") is Outcome.OPENED  # the first one is an hour old
    assert (windows.triggers, windows.in_cooldown, windows.over_hourly_limit) == (6, 1, 1)


# -- with DDS --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ros() -> Iterator[Ros]:
    with ros_session("recorder") as session:
        yield session


def drive(ros: Ros, plugin: Recorder, done: Any, step: Any = lambda: None) -> None:
    """Spin and poll as the measurement server does, until ``done()``."""

    def turn() -> None:
        step()
        plugin.on_poll(None)
        ros.harness.run_finished_work(plugin)

    assert ros.spin_until(done, turn)


def read_with_rosbags(path: str) -> dict[str, list[tuple[int, Any]]]:
    from rosbags.highlevel import AnyReader

    read: dict[str, list[tuple[int, Any]]] = {}
    with AnyReader([Path(path)]) as reader:
        for connection, timestamp, data in reader.messages():
            read.setdefault(connection.topic, []).append((timestamp, reader.deserialize(data, connection.msgtype)))
    return read


def test_an_incident_file_holds_the_window_of_odom_the_static_tf_and_the_reasons(ros: Ros, tmp_path: Path) -> None:
    odom_topic, static_topic, absent_topic = unique("/odom"), unique("/tf_static"), unique("/never")
    # A static transform published long before the recorder started: it must still be in the file.
    static = ros.node.create_publisher(type(tf_message()), static_topic, LATCHED)
    static.publish(tf_message(transform("map", "odom", 1.0, 2.0, 0.0)))
    odom = ros.node.create_publisher(Odometry, odom_topic, VOLATILE)
    plugin = ros.harness.make(
        Recorder,
        {
            "topics": [odom_topic, static_topic, absent_topic],
            "pre_trigger": 0.3,
            "post_trigger": 0.3,
            "cooldown": 600.0,  # the "third" trigger below falls in it however slowly the file is read
            "save_path": "incidents/%Y/incident",
            "compression": "lz4",
        },
        name="rec",
    )
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path), "robot1", {"minio": "prefix"})
    plugin.on_configure()
    plugin.on_activate()
    assert ros.spin_until(lambda: odom.get_subscription_count() == 1)
    assert plugin.counters()["messages"] == 1 or ros.spin_until(lambda: plugin.counters()["messages"] == 1)

    sent: list[tuple[int, int]] = []  # (index, wall time when published)
    triggers: dict[str, int] = {}

    def publish() -> None:
        i = len(sent)
        odom.publish(odometry(float(i), 0.0, 0.0))
        sent.append((i, time.time_ns()))
        time.sleep(0.005)  # a robot's 200 Hz at most
        if i == 80:
            triggers["first"] = time.time_ns()
            assert plugin.trigger("first") is Outcome.OPENED
        if i == 100:
            triggers["second"] = time.time_ns()
            assert plugin.trigger("second") is Outcome.EXTENDED

    emitted = ros.harness.context(plugin).emitted
    drive(ros, plugin, lambda: bool(emitted), publish)
    (incident,) = emitted
    record = incident.record
    assert_valid(Recorder, record)
    assert [t["reason"] for t in record["triggers"]] == ["first", "second"]
    assert record["start"] == pytest.approx((triggers["first"] - 0.3 * S) / S)
    assert record["end"] == pytest.approx((triggers["second"] + 0.3 * S) / S)
    path = record["local_paths"]["mcap"]
    year = Path(path).parent.name
    assert path == str(tmp_path / "robot1" / "incidents" / year / "incident.mcap")
    assert record["remote_paths"] == {"minio": {"mcap": f"robot1/prefix/incidents/{year}/incident.mcap"}}
    by_topic = {t["topic"]: t for t in record["topics"]}
    assert by_topic[absent_topic] == {
        "topic": absent_topic,
        "type": "",
        "messages": 0,
        "bytes": 0,
        "lost_to_memory_bound": 0,
        "lost_in_transport": 0,
        "absent": True,
    }
    assert by_topic[static_topic]["messages"] == 1 and by_topic[static_topic]["type"] == "tf2_msgs/msg/TFMessage"
    assert record["size"] == Path(path).stat().st_size and not record["cut_by_memory_bound"]
    assert stat.S_IMODE(Path(path).stat().st_mode) == 0o600  # the robot's data, DC's account's alone

    # The /odom messages of the window: those published in it, give or take one at each edge (the
    # receive time the ring keeps comes a little after the publish time measured here).
    read = read_with_rosbags(path)
    recorded = [int(message.pose.pose.position.x) for _, message in read[odom_topic]]
    assert recorded == list(range(recorded[0], recorded[-1] + 1)), "a gap in the window"
    start_ns, end_ns = triggers["first"] - 0.3 * S, triggers["second"] + 0.3 * S
    expected = [i for i, at in sent if start_ns <= at <= end_ns]
    assert abs(recorded[0] - expected[0]) <= 1 and abs(recorded[-1] - expected[-1]) <= 1
    assert by_topic[odom_topic]["messages"] == len(recorded)
    ((_, static_message),) = read[static_topic]
    assert static_message.transforms[0].transform.translation.y == 2.0

    # The mcap package reads it too: ros2 profile, ros2msg schemas, cdr messages.
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        assert {s.name: s.encoding for s in summary.schemas.values()} == {
            "nav_msgs/msg/Odometry": "ros2msg",
            "tf2_msgs/msg/TFMessage": "ros2msg",
        }
        assert summary.statistics is not None and summary.statistics.message_count == len(recorded) + 1

    # Within the cooldown after the window: counted, not recorded.
    assert plugin.trigger("third") is Outcome.COOLDOWN
    assert plugin.counters()["triggers_in_cooldown"] == 1 and plugin.counters()["incidents"] == 1
    warnings = ros.harness.context(plugin).logger.at("warning")
    assert any(absent_topic in w and "absent" in w for w in warnings)
    ros.harness.stop(plugin)


def test_the_service_the_topic_and_the_conditions_rising_edge_trigger(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/odom")
    plugin = ros.harness.make(
        Recorder, {"topics": [topic], "pre_trigger": 0.0, "post_trigger": 60.0}, name=unique("svc")
    )
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    plugin.on_activate()
    name = f"/dc/recorder/{ros.harness.context(plugin).name}/trigger"
    client = ros.node.create_client(Trigger, name)
    assert client.wait_for_service(timeout_sec=5.0)
    future = client.call_async(Trigger.Request())
    assert ros.spin_until(future.done)
    assert (future.result().success, future.result().message) == (True, "opened")
    reasons = ros.publisher(String, name, 10)
    reasons.publish(String(data="bumper hit"))
    assert ros.spin_until(lambda: plugin.counters()["triggers"] == 2)
    plugin.on_poll(True)  # false -> true: a trigger
    plugin.on_poll(True)  # still true: none
    plugin.on_poll(False)
    plugin.on_poll(True)  # a second rising edge
    open_incident = plugin._windows.open
    assert open_incident is not None
    assert [t.reason for t in open_incident.triggers] == ["service", "bumper hit", "conditions", "conditions"]
    ros.node.destroy_client(client)
    logger = ros.harness.context(plugin).logger
    ros.harness.stop(plugin)  # deactivate writes what the window holds, and says so
    assert len(list(tmp_path.rglob("*.mcap"))) == 1 and plugin.counters()["incidents_unpublished"] == 1
    assert any("saved at deactivate" in w for w in logger.at("warning"))


def test_the_memory_bound_cuts_the_window_and_the_record_says_so(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/odom")
    publisher = ros.node.create_publisher(Odometry, topic, VOLATILE)
    size = 1000
    plugin = ros.harness.make(
        Recorder,
        # Room for about 20 odometry messages (~720 bytes serialised, plus the ring's overhead per entry).
        {"topics": [topic], "pre_trigger": 10.0, "post_trigger": 0.5, "max_memory_mb": 20 * (size + 160) / 2**20},
    )
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    plugin.on_activate()
    assert ros.spin_until(lambda: publisher.get_subscription_count() == 1)
    count = [0]

    def publish() -> None:
        publisher.publish(odometry(float(count[0]), 0.0, 0.0))
        count[0] += 1
        if count[0] == 60:
            plugin.trigger("late")

    emitted = ros.harness.context(plugin).emitted
    drive(ros, plugin, lambda: bool(emitted), publish)
    record = emitted[0].record
    assert plugin._ring.bytes <= plugin._ring.max_bytes
    (warning,) = [w for w in ros.harness.context(plugin).logger.at("warning") if "max_memory_mb" in w]
    assert "less than pre_trigger (10 s)" in warning
    assert record["cut_by_memory_bound"] is True
    (entry,) = record["topics"]
    assert 0 < entry["messages"] <= 30
    assert plugin.counters()["lost_to_bound"] > 0
    # Every message received is in the file, still in the ring, or counted as let go (none is older than
    # pre_trigger); the file's messages the ring let go while it was written were not lost.
    in_both = len(plugin._ring.between(int(record["start"] * S), int(record["end"] * S)))
    in_file_or_ring = entry["messages"] + len(plugin._ring) - in_both
    assert plugin.counters()["messages"] == in_file_or_ring + plugin.counters()["lost_to_bound"]
    ros.harness.stop(plugin)


def test_a_type_without_definition_is_written_without_schema_and_named(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    from dc_measurements.recorder.definitions import Definitions
    from dc_measurements.recorder.mcap_file import Channel, write_mcap

    definitions = Definitions()
    channels: list[Channel | None] = [
        Channel("/odom", "nav_msgs/msg/Odometry"),
        Channel("/custom", "no_such_pkg/msg/Thing"),
        None,  # a topic never seen
    ]
    path = tmp_path / "x.mcap"
    entries = [(2 * S, 1 * S, 0, b"\x00\x01\x00\x00odom"), (3 * S, 0, 1, b"\x00\x01\x00\x00raw")]
    written = write_mcap(str(path), channels, entries, "zstd", definitions.get)
    assert written.without_definition == ["no_such_pkg/msg/Thing"] and written.size == path.stat().st_size
    with path.open("rb") as stream:
        reader = make_reader(stream)
        read = [
            (channel.topic, schema.name if schema else None, message.data)
            for schema, channel, message in reader.iter_messages()
        ]
    assert read == [("/odom", "nav_msgs/msg/Odometry", entries[0][3]), ("/custom", None, entries[1][3])]
    assert not list(tmp_path.glob("*.part"))


def test_a_file_that_cannot_be_written_is_kept_and_tried_again_then_dropped_counted(
    ros: Ros, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import dc_measurements.recorder as recorder_module

    monkeypatch.setattr(recorder_module, "WRITE_RETRY_NS", 0)
    topic = unique("/odom")
    publisher = ros.node.create_publisher(Odometry, topic, VOLATILE)
    plugin = ros.harness.make(Recorder, {"topics": [topic], "pre_trigger": 5.0, "post_trigger": 0.0})
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    # A file where the incidents' folder should be (a full disk fails the same way): no file can be written.
    blocker = tmp_path / "incidents"
    blocker.write_text("not a folder")
    plugin.on_configure()
    plugin.on_activate()
    assert ros.spin_until(lambda: publisher.get_subscription_count() == 1)
    for i in range(5):
        publisher.publish(odometry(float(i), 0.0, 0.0))
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 5)
    counters = plugin.counters
    emitted = ros.harness.context(plugin).emitted

    def poll() -> None:
        plugin.on_poll(None)
        ros.harness.run_finished_work(plugin)

    plugin.trigger("first")
    assert ros.spin_until(lambda: counters()["incidents_dropped"] == 1, poll)
    assert counters()["write_errors"] == recorder_module.WRITE_TRIES and not emitted

    plugin.trigger("second")
    assert ros.spin_until(lambda: counters()["write_errors"] == recorder_module.WRITE_TRIES + 1, poll)
    blocker.unlink()  # room again: the kept window is written at its next try
    assert ros.spin_until(lambda: bool(emitted), poll)
    assert emitted[0].record["messages"] == 5 and emitted[0].record["triggers"][0]["reason"] == "second"
    # Every window opened is in a file or counted as dropped.
    assert counters()["triggers"] == counters()["incidents"] + counters()["incidents_dropped"] == 2
    ros.harness.stop(plugin)


def test_a_topic_that_appears_after_the_recorder_started_is_recorded_from_its_first_message(
    ros: Ros, tmp_path: Path
) -> None:
    # /odom's type given, /tf's learnt from the graph (a condition of the server subscribes to it first),
    # the camera best effort (as sensor drivers publish) and the static transforms latched: none of them
    # has a publisher when the recorder is configured. (No poll before the end: the window stays open.)
    odom_topic, tf_topic, camera_topic, static_topic = (
        unique(t) for t in ("/odom", "/tf", "/camera/compressed", "/tf_static")
    )
    tf_type = type(tf_message())
    ros.node.create_subscription(tf_type, tf_topic, lambda _: None, VOLATILE)
    plugin = ros.harness.make(
        Recorder,
        {
            "topics": [odom_topic, tf_topic, camera_topic, static_topic],
            "types": ["nav_msgs/msg/Odometry", "", "std_msgs/msg/String", "tf2_msgs/msg/TFMessage"],
            "pre_trigger": 5.0,
            "post_trigger": 0.2,
        },
    )
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    plugin.on_activate()
    # Subscribed at configure, before any publisher: no graph check to wait for.
    assert ros.node.count_subscribers(odom_topic) == 1 and ros.node.count_subscribers(tf_topic) == 2
    odom = ros.publisher(Odometry, odom_topic, VOLATILE)
    tf = ros.publisher(tf_type, tf_topic, VOLATILE, subscribers=2)
    odom.publish(odometry(0.0, 0.0, 0.0))
    tf.publish(tf_message(transform("odom", "base_link", 0.0, 0.0, 0.0)))
    assert plugin.trigger("right away") is Outcome.OPENED
    # Best effort and volatile, the early subscriptions match every publisher: a best-effort camera's too.
    camera = ros.publisher(String, camera_topic, QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT))
    static = ros.publisher(tf_type, static_topic, LATCHED)
    static.publish(tf_message(transform("map", "odom", 1.0, 2.0, 0.0)))
    camera.publish(String(data="frame"))
    odom.publish(odometry(1.0, 0.0, 0.0))
    # The graph check gives the reliable and the latching publishers a subscription of their QoS, and keeps
    # the early one until that one takes its first message: a message both take (the latched one resent) is
    # kept once.
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 5)  # odom 0 and 1, tf, static, camera
    plugin._discover()
    assert ros.node.count_subscribers(odom_topic) == 2 and ros.node.count_subscribers(static_topic) == 2
    assert ros.spin_until(lambda: odom.get_subscription_count() == 2)
    for i in range(2, 5):
        odom.publish(odometry(float(i), 0.0, 0.0))
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 8)
    assert ros.spin_until(
        lambda: ros.node.count_subscribers(odom_topic) == 1 and ros.node.count_subscribers(static_topic) == 1
    )
    assert plugin.trigger("then") is Outcome.EXTENDED
    emitted = ros.harness.context(plugin).emitted
    drive(ros, plugin, lambda: bool(emitted))
    record = emitted[0].record
    read = read_with_rosbags(record["local_paths"]["mcap"])
    assert [int(m.pose.pose.position.x) for _, m in read[odom_topic]] == [0, 1, 2, 3, 4]
    assert len(read[tf_topic]) == 1 and [m.data for _, m in read[camera_topic]] == ["frame"]
    # The latched message once, though the early subscription may have taken it before the one that
    # asks the publisher for its history.
    ((_, static_message),) = read[static_topic]
    assert static_message.transforms[0].transform.translation.y == 2.0
    by_topic = {t["topic"]: t for t in record["topics"]}
    assert [by_topic[t]["absent"] for t in (odom_topic, tf_topic, camera_topic, static_topic)] == [False] * 4
    assert by_topic[tf_topic]["type"] == "tf2_msgs/msg/TFMessage"
    ros.harness.stop(plugin)


def _early_recorder(ros: Ros, tmp_path: Path, topic: str) -> Recorder:
    """A recorder of ``topic`` (its type given) configured before the topic has a publisher: subscribed best
    effort, DEPTH deep, and no graph check but those the test makes (no poll)."""
    plugin = ros.harness.make(
        Recorder, {"topics": [topic], "types": ["nav_msgs/msg/Odometry"], "pre_trigger": 60.0, "post_trigger": 0.1}
    )
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def _matched_without_spinning(publisher: Any, subscriptions: int) -> None:
    # Spinning would take what the test wants left queued in the recorder's subscriptions.
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() < subscriptions:
        assert time.monotonic() < deadline, "not matched"
        time.sleep(0.01)


def test_messages_the_middleware_drops_before_the_recorder_takes_them_are_counted(ros: Ros, tmp_path: Path) -> None:
    from dc_measurements.recorder import DEPTH

    topic = unique("/odom")
    plugin = _early_recorder(ros, tmp_path, topic)
    odom = ros.publisher(Odometry, topic, VOLATILE)
    odom.publish(odometry(0.0, 0.0, 0.0))
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 1)
    # A burst while the server's loop is busy elsewhere (nothing spins): the subscription's queue keeps its
    # newest DEPTH, the middleware drops the rest and says nothing (rmw_fastrtps raises no message_lost event).
    sent = 1 + 3 * DEPTH
    for i in range(1, sent):
        odom.publish(odometry(float(i), 0.0, 0.0))
    counters = plugin.counters
    assert ros.spin_until(lambda: counters()["messages"] + counters()["lost_in_transport"] == sent)
    assert counters()["lost_in_transport"] >= 2 * DEPTH
    assert plugin.trigger("after the burst") is Outcome.OPENED
    emitted = ros.harness.context(plugin).emitted
    drive(ros, plugin, lambda: bool(emitted))
    ((entry,),) = [emitted[0].record["topics"]]
    assert entry["messages"] == counters()["messages"] and entry["lost_in_transport"] == counters()["lost_in_transport"]
    assert "transport_losses_unchecked" not in entry
    # The newest were kept: the last message published is in the file.
    read = read_with_rosbags(emitted[0].record["local_paths"]["mcap"])
    assert read[topic][-1][1].pose.pose.position.x == sent - 1
    ros.harness.stop(plugin)


def test_a_topic_with_two_publishers_is_said_unchecked_not_counted_as_losses(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/odom")
    first = ros.node.create_publisher(Odometry, topic, VOLATILE)
    second = ros.node.create_publisher(Odometry, topic, VOLATILE)
    plugin = ros.harness.make(Recorder, {"topics": [topic], "pre_trigger": 60.0, "post_trigger": 0.1})
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    plugin.on_activate()
    assert ros.spin_until(lambda: first.get_subscription_count() == 1 and second.get_subscription_count() == 1)
    # Their sequence numbers interleave (1..10, then 1, 11, 2, 12...): read as one stream, gaps that are none.
    for i in range(10):
        first.publish(odometry(float(i), 0.0, 0.0))
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 10)
    for i in range(5):
        second.publish(odometry(100.0 + i, 0.0, 0.0))
        first.publish(odometry(10.0 + i, 0.0, 0.0))
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 20)
    assert plugin.counters()["lost_in_transport"] == 0
    assert plugin.trigger("two publishers") is Outcome.OPENED
    emitted = ros.harness.context(plugin).emitted
    drive(ros, plugin, lambda: bool(emitted))
    ((entry,),) = [emitted[0].record["topics"]]
    assert entry["messages"] == 20 and entry["lost_in_transport"] == 0 and entry["transport_losses_unchecked"]
    ros.harness.stop(plugin)


def test_the_handover_takes_what_the_early_subscription_still_holds(ros: Ros, tmp_path: Path) -> None:
    topic = unique("/odom")
    plugin = _early_recorder(ros, tmp_path, topic)
    odom = ros.publisher(Odometry, topic, VOLATILE)
    for i in range(5):
        odom.publish(odometry(float(i), 0.0, 0.0))  # queued in the early subscription: nothing spins
    plugin._discover()  # the publisher is reliable: a subscription of its QoS beside the early one
    _matched_without_spinning(odom, 2)
    for i in range(5, 10):
        odom.publish(odometry(float(i), 0.0, 0.0))  # both subscriptions hold these
    # Graph checks come and go (once a second on a robot) while the loop is busy: the early subscription stays
    # until the new one takes its first message, and what it holds is taken before it goes.
    plugin._discover()
    plugin._discover()
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 10)
    assert ros.spin_until(lambda: ros.node.count_subscribers(topic) == 1)
    assert plugin.trigger("after the handover") is Outcome.OPENED
    emitted = ros.harness.context(plugin).emitted
    drive(ros, plugin, lambda: bool(emitted))
    read = read_with_rosbags(emitted[0].record["local_paths"]["mcap"])
    assert [int(m.pose.pose.position.x) for _, m in read[topic]] == list(range(10))
    assert plugin.counters()["lost_in_transport"] == 0
    ros.harness.stop(plugin)


def test_types_needs_one_entry_per_topic() -> None:
    from dc_core.errors import ConfigError
    from dc_core.params import parse_params
    from dc_measurements.recorder import RecorderParams

    with pytest.raises(ConfigError, match=r"incidents\.types: one entry per topic \(2\), not 1"):
        parse_params(RecorderParams, {"topics": ["/a", "/b"], "types": ["x/msg/Y"]}, "incidents")


def test_without_conditions_an_idle_recorder_has_no_timer_running_and_polls_itself_while_a_window_needs_it(
    ros: Ros, tmp_path: Path
) -> None:
    topic = unique("/odom")
    odom = ros.node.create_publisher(Odometry, topic, VOLATILE)
    plugin = ros.harness.make(Recorder, {"topics": [topic], "pre_trigger": 1.0, "post_trigger": 0.1})
    plugin.has_trigger_conditions = False  # as the server sets it for a measurement without conditions
    assert not plugin.timer_driven  # the server makes no timer for it
    ros.harness.context(plugin).paths = BasePaths(str(tmp_path))
    plugin.on_configure()
    plugin.on_activate()
    timers = plugin._poll_timer, plugin._discovery_timer
    # Its topic subscribed at configure: nothing to poll, nothing to look for in the graph.
    assert all(t.is_canceled() for t in timers)
    assert ros.spin_until(lambda: odom.get_subscription_count() == 1)
    odom.publish(odometry(1.0, 0.0, 0.0))
    assert ros.spin_until(lambda: plugin.counters()["messages"] == 1)
    assert plugin.trigger("bumper") is Outcome.OPENED and not timers[0].is_canceled()
    emitted = ros.harness.context(plugin).emitted

    # Only spinning: the recorder's own timer closes the window and writes it, then stops.
    def written() -> None:
        ros.harness.run_finished_work(plugin)

    assert ros.spin_until(lambda: bool(emitted) and timers[0].is_canceled(), written)
    assert emitted[0].record["messages"] == 1
    ros.harness.stop(plugin)
    assert plugin._poll_timer is None
