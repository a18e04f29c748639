"""The simulated topics: deterministic bytes, rates, time order and stamps, and frames that
match what robot_state_publisher would compute from the URDF."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import yourdfpy
from numpy.typing import NDArray

from host_bridge.demo import messages, robot
from tests.host_bridge.demo.support import Messages, log_stamp_ns, stamp_ns


def test_simulate_is_deterministic() -> None:
    first = list(messages.simulate(3.0))
    second = list(messages.simulate(3.0))
    assert first == second
    assert {m.topic for m in first} == {spec.topic for spec in messages.TOPICS}
    assert len({m.data for m in first if m.topic == "/scan"}) == 15  # the scans do change
    assert len({m.data for m in first if m.topic == "/camera/image_raw"}) == 15
    # a topic subset is the same bytes as the full run's messages of those topics
    subset = list(messages.simulate(3.0, topics={"/map", "/odom"}))
    assert subset == [m for m in first if m.topic in ("/map", "/odom")]


def test_rates_order_and_stamps() -> None:
    store = messages.typestore()
    msgs = list(messages.simulate(10.0, start_ns=5_000_000_000))
    counts = Counter(m.topic for m in msgs)
    for topic in ("/tf", "/odom", "/joint_states", "/imu", messages.STEP_TIMER_TOPIC):
        assert counts[topic] == 300, topic
    for topic in ("/scan", "/camera/image_raw", "/camera/camera_info", "/camera/depth/image_raw",
                  "/camera/depth/points"):
        assert counts[topic] == 50, topic
    assert counts["/map"] == counts["/battery_state"] == 10
    assert counts["/tf_static"] == counts["/robot_description"] == 1
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
    assert set(got) == {*fixed, "odom"}
    assert got["odom"].header.frame_id == "map"
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
