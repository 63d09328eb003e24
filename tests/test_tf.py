"""DC's TF buffer (dc_core.tf) against chains computed by hand; no ROS needed."""

from __future__ import annotations

import math
import threading

import pytest

from dc_core.tf import Transform, TransformBuffer, TransformError, interpolate, quaternion_from_yaw

S = 1_000_000_000  # nanoseconds per second
DEG = math.pi / 180


def assert_pose(t: Transform, x: float, y: float, yaw: float, z: float = 0.0) -> None:
    assert t.translation == pytest.approx((x, y, z), abs=1e-9)
    # Compare angles on the circle: pi and -pi are the same heading.
    assert math.remainder(t.yaw - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def robot(cache_s: float = 10.0) -> TransformBuffer:
    """map -> odom (static), odom -> base_link (dynamic, 1 s and 2 s), base_link -> laser and camera (static)."""
    buffer = TransformBuffer(cache_s)
    buffer.set_transform("map", "odom", 0, Transform.from_xy_yaw(1, 2, 90 * DEG), static=True)
    buffer.set_transform("odom", "base_link", 1 * S, Transform.from_xy_yaw(3, 0, 0))
    buffer.set_transform("odom", "base_link", 2 * S, Transform.from_xy_yaw(4, 0, 0))
    buffer.set_transform("base_link", "laser", 0, Transform.from_xy_yaw(0.5, 0, 180 * DEG), static=True)
    camera = Transform((0.0, 0.2, 1.0), quaternion_from_yaw(-90 * DEG))
    buffer.set_transform("base_link", "camera", 0, camera, static=True)
    return buffer


# --- Transform arithmetic ---


def test_apply_translates_then_rotates_by_hand() -> None:
    t = Transform.from_xy_yaw(1, 0, 90 * DEG)
    assert t.apply((1.0, 0.0, 0.0)) == pytest.approx((1.0, 1.0, 0.0))
    assert t.apply((0.0, 0.0, 2.0)) == pytest.approx((1.0, 0.0, 2.0))


def test_compose_applies_other_first_then_self() -> None:
    a = Transform.from_xy_yaw(1, 0, 90 * DEG)
    b = Transform((0.0, 2.0, 0.5), quaternion_from_yaw(30 * DEG))
    p = (0.3, -1.2, 0.7)
    assert a.compose(b).apply(p) == pytest.approx(a.apply(b.apply(p)))
    # Hand computed: b's origin (0, 2) rotated by 90 deg is (-2, 0), plus (1, 0).
    assert_pose(a.compose(b), -1, 0, 120 * DEG, z=0.5)


def test_compose_with_inverse_is_identity() -> None:
    t = Transform((1.0, -2.0, 3.0), (0.1, 0.2, 0.3, 0.9))
    for identity in (t.compose(t.inverse()), t.inverse().compose(t)):
        assert identity.translation == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)
        assert abs(identity.rotation[3]) == pytest.approx(1.0)
    assert t.inverse().apply(t.apply((4.0, 5.0, 6.0))) == pytest.approx((4.0, 5.0, 6.0))


@pytest.mark.parametrize("yaw", [0.0, 0.5, -0.5, 2.0, -2.0, math.pi - 1e-6, -math.pi + 1e-6, math.pi])
def test_yaw_round_trips(yaw: float) -> None:
    assert Transform.from_xy_yaw(0, 0, yaw).yaw == pytest.approx(yaw)


def test_yaw_of_minus_pi_is_pi() -> None:
    assert Transform.from_xy_yaw(0, 0, -math.pi).yaw == pytest.approx(math.pi)


def test_slerp_across_pi_takes_the_short_way() -> None:
    a, b = Transform.from_xy_yaw(0, 0, 170 * DEG), Transform.from_xy_yaw(2, 0, -170 * DEG)
    assert abs(interpolate(a, b, 0.5).yaw) == pytest.approx(math.pi)
    assert_pose(interpolate(a, b, 0.25), 0.5, 0, 175 * DEG)
    assert_pose(interpolate(a, b, 0.0), 0, 0, 170 * DEG)
    assert_pose(interpolate(a, b, 1.0), 2, 0, -170 * DEG)


def test_interpolate_nearly_equal_rotations_is_finite() -> None:
    a, b = Transform.from_xy_yaw(0, 0, 0.1), Transform.from_xy_yaw(0, 0, 0.1 + 1e-9)
    assert interpolate(a, b, 0.5).yaw == pytest.approx(0.1)


# --- Chains ---


def test_chain_with_statics_and_dynamics() -> None:
    buffer = robot()
    # laser origin (0.5, 0) in base_link -> (3.5, 0) in odom -> rotated 90 deg (0, 3.5) + (1, 2) in map.
    map_laser = buffer.lookup("map", "laser", 1 * S)
    assert_pose(map_laser, 1, 5.5, -90 * DEG)
    # The laser's point 1 m ahead, followed link by link: (-0.5, 0) in base_link, (2.5, 0) in odom, (1, 4.5) in map.
    assert map_laser.apply((1.0, 0.0, 0.0)) == pytest.approx((1.0, 4.5, 0.0))


def test_reverse_lookup_is_the_inverse() -> None:
    buffer = robot()
    laser_map = buffer.lookup("laser", "map", 1 * S)
    assert laser_map.apply((1.0, 4.5, 0.0)) == pytest.approx((1.0, 0.0, 0.0))
    forward = buffer.lookup("map", "laser", 1 * S)
    assert_pose(laser_map.compose(forward), 0, 0, 0)


def test_siblings_go_through_their_common_parent() -> None:
    # camera at (0, 0.2, 1) yaw -90 in base_link; seen from the laser (0.5, 0, yaw 180): (0.5, -0.2, 1), yaw 90.
    assert_pose(robot().lookup("laser", "camera", 1 * S), 0.5, -0.2, 90 * DEG, z=1.0)


def test_static_only_chain_answers_at_any_time() -> None:
    buffer = robot()
    for time_ns in (0, 1, 1000 * S):
        assert_pose(buffer.lookup("base_link", "laser", time_ns), 0.5, 0, 180 * DEG)
    assert buffer.latest_time("base_link", "laser") == 0


def test_same_frame_is_identity_even_unknown() -> None:
    buffer = robot()
    assert buffer.lookup("laser", "laser") == Transform()
    assert buffer.lookup("nowhere", "nowhere") == Transform()


def test_leading_slash_is_stripped() -> None:
    buffer = TransformBuffer()
    buffer.set_transform("/map", "/odom", 0, Transform.from_xy_yaw(1, 0, 0), static=True)
    assert buffer.frames() == {"map", "odom"}
    assert_pose(buffer.lookup("/map", "odom"), 1, 0, 0)


def test_parent_equal_to_child_is_rejected() -> None:
    with pytest.raises(ValueError, match="distinct"):
        TransformBuffer().set_transform("map", "/map", 0, Transform())


# --- Time ---


def test_interpolation_between_samples() -> None:
    buffer = TransformBuffer()
    buffer.set_transform("odom", "base_link", 1 * S, Transform.from_xy_yaw(0, 0, 0))
    buffer.set_transform("odom", "base_link", 2 * S, Transform.from_xy_yaw(1, 0, math.pi / 2))
    assert_pose(buffer.lookup("odom", "base_link", 1_500_000_000), 0.5, 0, math.pi / 4)
    assert_pose(buffer.lookup("odom", "base_link", 1 * S), 0, 0, 0)
    assert_pose(buffer.lookup("odom", "base_link", 2 * S), 1, 0, math.pi / 2)


def test_out_of_order_samples_are_sorted() -> None:
    buffer = TransformBuffer()
    for seconds in (3, 1, 2):
        buffer.set_transform("odom", "base_link", seconds * S, Transform.from_xy_yaw(seconds, 0, 0))
    assert_pose(buffer.lookup("odom", "base_link", 1_500_000_000), 1.5, 0, 0)
    assert_pose(buffer.lookup("odom", "base_link", 2_500_000_000), 2.5, 0, 0)
    assert buffer.latest_time("odom", "base_link") == 3 * S


def test_time_zero_is_latest_common_time() -> None:
    buffer = TransformBuffer()
    for seconds in (1, 2, 3):
        buffer.set_transform("map", "odom", seconds * S, Transform.from_xy_yaw(seconds, 0, 0))
    for seconds in (1, 2):
        buffer.set_transform("odom", "base_link", seconds * S, Transform.from_xy_yaw(0, seconds, 0))
    buffer.set_transform("base_link", "laser", 0, Transform.from_xy_yaw(0, 0, 0), static=True)
    assert buffer.latest_time("map", "laser") == 2 * S
    assert buffer.latest_time("laser", "map") == 2 * S
    assert buffer.latest_time("map", "odom") == 3 * S
    assert_pose(buffer.lookup("map", "laser"), 2, 2, 0)
    assert_pose(buffer.lookup("map", "odom"), 3, 0, 0)


def test_tolerance_into_the_future() -> None:
    buffer = robot()
    assert_pose(buffer.lookup("odom", "base_link", 2_050_000_000, tolerance_ns=S // 10), 4, 0, 0)
    with pytest.raises(TransformError) as error:
        buffer.lookup("map", "laser", 2_200_000_000, tolerance_ns=S // 10)
    message = str(error.value)
    assert message.startswith("no transform from 'map' to 'laser': extrapolation into the future")
    assert "0.2 s after the newest transform odom -> base_link" in message
    with pytest.raises(TransformError, match="future"):
        buffer.lookup("map", "laser", 2 * S + 1)


def test_tolerance_into_the_past() -> None:
    buffer = robot()
    assert_pose(buffer.lookup("odom", "base_link", 950_000_000, tolerance_ns=S // 10), 3, 0, 0)
    with pytest.raises(TransformError) as error:
        buffer.lookup("map", "laser", 800_000_000, tolerance_ns=S // 10)
    message = str(error.value)
    assert "extrapolation into the past" in message
    assert "0.2 s before the oldest transform odom -> base_link" in message


def test_cache_drops_old_samples() -> None:
    buffer = TransformBuffer(cache_s=1.0)
    for half_seconds in range(7):  # 0 s .. 3 s
        stamp = half_seconds * S // 2
        buffer.set_transform("odom", "base_link", stamp, Transform.from_xy_yaw(half_seconds, 0, 0))
    assert_pose(buffer.lookup("odom", "base_link", 2 * S), 4, 0, 0)
    with pytest.raises(TransformError, match="past"):
        buffer.lookup("odom", "base_link", 1_500_000_000)
    # A late sample older than the cache window is not let back in.
    buffer.set_transform("odom", "base_link", 1 * S, Transform.from_xy_yaw(2, 0, 0))
    assert buffer.can_transform("odom", "base_link", 1 * S) is not None


def test_clear_keeps_statics_and_forgets_dynamics() -> None:
    buffer = robot()
    buffer.clear()
    assert_pose(buffer.lookup("base_link", "laser"), 0.5, 0, 180 * DEG)
    assert_pose(buffer.lookup("map", "odom"), 1, 2, 90 * DEG)
    assert buffer.can_transform("odom", "base_link", 1 * S) is not None
    # After a bag restart time starts over: earlier stamps are accepted again.
    buffer.set_transform("odom", "base_link", 1, Transform.from_xy_yaw(7, 0, 0))
    assert_pose(buffer.lookup("map", "laser"), 1, 9.5, -90 * DEG)


def test_new_static_replaces_old() -> None:
    buffer = robot()
    buffer.set_transform("base_link", "laser", 0, Transform.from_xy_yaw(0.1, 0, 0), static=True)
    assert_pose(buffer.lookup("base_link", "laser"), 0.1, 0, 0)


def test_parent_of_most_recent_sample_wins() -> None:
    buffer = robot()
    buffer.set_transform("map", "base_link", 5 * S, Transform.from_xy_yaw(9, 9, 0))
    assert_pose(buffer.lookup("map", "base_link"), 9, 9, 0)
    assert buffer.latest_time("map", "laser") == 5 * S
    # A late sample under the old parent does not switch it back.
    buffer.set_transform("odom", "base_link", 3 * S, Transform.from_xy_yaw(0, 0, 0))
    assert_pose(buffer.lookup("map", "base_link", 5 * S), 9, 9, 0)


# --- Failures ---


def test_unknown_frame() -> None:
    buffer = robot()
    assert buffer.can_transform("map", "nowhere") == "no transform from 'map' to 'nowhere': frame 'nowhere' is unknown"
    with pytest.raises(TransformError, match="frame 'nowhere' is unknown"):
        buffer.lookup("nowhere", "map")


def test_disconnected_trees() -> None:
    buffer = robot()
    buffer.set_transform("world", "robot2", 0, Transform(), static=True)
    with pytest.raises(TransformError) as error:
        buffer.lookup("map", "robot2")
    assert str(error.value) == (
        "no transform from 'map' to 'robot2': 'map' and 'robot2' are not connected (trees rooted at 'map' and 'world')"
    )
    with pytest.raises(TransformError):
        buffer.latest_time("map", "robot2")


def test_can_transform_and_frames() -> None:
    buffer = robot()
    assert buffer.can_transform("map", "laser", 1 * S) is None
    assert buffer.frames() == {"map", "odom", "base_link", "laser", "camera"}


def test_parent_loop_raises_instead_of_hanging() -> None:
    buffer = TransformBuffer()
    buffer.set_transform("a", "b", 0, Transform(), static=True)
    buffer.set_transform("b", "c", 0, Transform(), static=True)
    buffer.set_transform("c", "a", 0, Transform(), static=True)
    buffer.set_transform("c", "d", 0, Transform(), static=True)
    result: list[str | None] = []
    worker = threading.Thread(target=lambda: result.append(buffer.can_transform("d", "b")), daemon=True)
    worker.start()
    worker.join(timeout=5)
    assert not worker.is_alive()
    assert result[0] is not None and "loop" in result[0]
