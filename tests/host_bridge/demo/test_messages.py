"""The simulated topics: deterministic bytes, rates, time order and stamps, frames that match
what robot_state_publisher would compute from the URDF, no map of the robot's own, and the
ground truth beside its odometry."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import pytest
import yourdfpy
from numpy.typing import NDArray

from host_bridge.demo import messages, robot, world
from tests.host_bridge.demo.support import SHORT_S, Messages, log_stamp_ns, stamp_ns, track


def test_simulate_is_deterministic() -> None:
    first = list(messages.simulate(3.0))
    second = list(messages.simulate(3.0))
    assert first == second
    assert {m.topic for m in first} == {spec.topic for spec in messages.TOPICS}
    assert len({m.data for m in first if m.topic == "/scan"}) == 15  # the scans do change
    assert len({m.data for m in first if m.topic == "/camera/image_raw"}) == 15
    # a topic subset is the same bytes as the full run's messages of those topics
    subset = list(messages.simulate(3.0, topics={messages.GROUND_TRUTH_WALLS_TOPIC, "/odom"}))
    assert subset == [m for m in first if m.topic in (messages.GROUND_TRUTH_WALLS_TOPIC, "/odom")]
    assert len(subset) == 1 + 3 * robot.TICK_HZ


def test_rates_order_and_stamps() -> None:
    store = messages.typestore()
    msgs = list(messages.simulate(10.0, start_ns=5_000_000_000))
    counts = Counter(m.topic for m in msgs)
    for topic in ("/tf", "/odom", "/joint_states", "/imu", messages.STEP_TIMER_TOPIC,
                  messages.GROUND_TRUTH_POSE_TOPIC):
        assert counts[topic] == 300, topic
    for topic in ("/scan", "/camera/image_raw", "/camera/camera_info", "/camera/depth/image_raw",
                  "/camera/depth/points"):
        assert counts[topic] == 50, topic
    assert counts["/battery_state"] == 10
    assert counts["/tf_static"] == counts["/robot_description"] == 1
    assert counts[messages.GROUND_TRUTH_WALLS_TOPIC] == 1
    assert 2 <= counts["/rosout"] <= 6
    assert msgs[0].topic == "/tf_static"
    assert msgs[0].log_ns == 5_000_000_000
    log_times = [m.log_ns for m in msgs]
    assert log_times == sorted(log_times)
    assert log_times[-1] < 5_000_000_000 + 10_000_000_000
    types = {m.topic: m.msgtype for m in msgs}
    assert types == {spec.topic: spec.msgtype for spec in messages.TOPICS}
    for m in msgs:
        decoded: Any = store.deserialize_cdr(m.data, m.msgtype)
        if m.topic in ("/tf", "/tf_static"):
            stamps = [stamp_ns(t.header) for t in decoded.transforms]
        elif m.topic == "/rosout":
            stamps = [log_stamp_ns(decoded)]
        elif hasattr(decoded, "header"):
            stamps = [stamp_ns(decoded.header)]
        else:  # std_msgs String / Float32 have no stamp
            continue
        assert stamps, m.topic
        assert all(s == m.log_ns for s in stamps), m.topic


def test_static_and_wheel_frames_match_the_urdf(short: Messages, urdf: yourdfpy.URDF) -> None:
    ((_, description),) = short["/robot_description"]
    assert description.data == robot.robot_description()
    ((_, static),) = short["/tf_static"]
    fixed = {j.child: j for j in urdf.robot.joints if j.type == "fixed"}
    got = {t.child_frame_id: t for t in static.transforms}
    assert set(got) == set(fixed)  # no map -> odom: placing map is the host's SLAM's job
    for child, joint in fixed.items():
        t = got[child]
        assert t.header.frame_id == joint.parent
        np.testing.assert_allclose(
            _matrix(t.transform), urdf.get_transform(child, joint.parent), atol=1e-12
        )

    _, tf = short["/tf"][100]
    _, joints = short["/joint_states"][100]
    frames = {t.child_frame_id: t for t in tf.transforms}
    assert frames["base_footprint"].header.frame_id == "odom"
    assert list(joints.name) == ["wheel_left_joint", "wheel_right_joint"]
    assert np.all(np.asarray(joints.position) > 1.0)  # the wheels have turned
    # /tf carries what robot_state_publisher computes from the joint angles and the URDF
    urdf.update_cfg(dict(zip(joints.name, joints.position, strict=True)))
    for name in joints.name:
        child = urdf.joint_map[name].child
        assert frames[child].header.frame_id == "base_link"
        np.testing.assert_allclose(
            _matrix(frames[child].transform), urdf.get_transform(child, "base_link"), atol=1e-9
        )


def _matrix(transform: Any) -> NDArray[np.float64]:
    q, p = transform.rotation, transform.translation
    x, y, z, w = q.x, q.y, q.z, q.w
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = [p.x, p.y, p.z]
    return m


def test_the_robot_publishes_no_map_and_no_map_frame(short: Messages) -> None:
    """Like a robot that runs no SLAM: no grid, and no transform names ``map``; the ground
    truth is the only thing in ``map``, the apartment's frame."""
    types = {spec.topic: spec.msgtype for spec in messages.TOPICS}
    assert "/map" not in types
    assert not any("OccupancyGrid" in msgtype for msgtype in types.values())
    frames = {
        (t.header.frame_id, t.child_frame_id)
        for topic in ("/tf", "/tf_static") for _, tf in short[topic] for t in tf.transforms
    }
    assert ("odom", "base_footprint") in frames
    assert not any("map" in pair for pair in frames)
    in_map = {topic for topic, run in short.items()
              if any(getattr(getattr(m, "header", None), "frame_id", None) == "map" for _, m in run)}
    assert in_map == {messages.GROUND_TRUTH_POSE_TOPIC, messages.GROUND_TRUTH_WALLS_TOPIC}


def test_ground_truth_walls_are_the_world_walls(short: Messages) -> None:
    ((log_ns, marker),) = short[messages.GROUND_TRUTH_WALLS_TOPIC]
    assert log_ns == messages.DEFAULT_START_NS  # once, at the start, latched (see test_bag)
    assert (marker.header.frame_id, marker.type, marker.action) == ("map", 5, 0)  # LINE_LIST, ADD
    assert stamp_ns(marker.header) == log_ns
    assert (marker.lifetime.sec, marker.lifetime.nanosec) == (0, 0)  # for ever
    assert (marker.pose.position.x, marker.pose.position.y, marker.pose.position.z) == (0, 0, 0)
    assert marker.pose.orientation.w == 1.0
    assert marker.scale.x == messages.GROUND_TRUTH_WALLS_WIDTH
    assert (marker.color.r, marker.color.g, marker.color.b, marker.color.a) == pytest.approx(
        messages.GROUND_TRUTH_WALLS_RGBA)
    points = np.array([(p.x, p.y, p.z) for p in marker.points])
    assert points.shape == (2 * len(world.WALLS), 3)
    np.testing.assert_array_equal(points[:, :2].reshape(-1, 2, 2), world.WALLS)
    # above the walls the host raises on a map (GridOptions.wall_height, 0.5 m)
    np.testing.assert_allclose(points[:, 2], 0.52, rtol=1e-12)


def test_ground_truth_pose_is_the_true_track(short: Messages) -> None:
    truth = list(robot.odometry_track(SHORT_S))
    poses = short[messages.GROUND_TRUTH_POSE_TOPIC]
    assert [log_ns for log_ns, _ in poses] == [
        messages.tick_stamp_ns(tick) for tick in range(len(truth))]
    assert {m.header.frame_id for _, m in poses} == {"map"}
    assert all(stamp_ns(m.header) == log_ns for log_ns, m in poses)
    expected = np.array([(state.x, state.y, state.yaw) for state, _ in truth])
    np.testing.assert_allclose(track(short, messages.GROUND_TRUTH_POSE_TOPIC), expected, atol=1e-12)
    assert {m.pose.position.z for _, m in poses} == {0.0}
