"""The simulated robot: exact ray casting, rates, determinism, a readable bag, and a trajectory
and scans that agree with the world geometry they came from."""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.interfaces import ConnectionExtRosbag2, QosDurability

from host_bridge import sim
from host_bridge.errors import InputError

LAP_S = 65.0  # one full lap of the loop takes about 62 s


def _distance_to_walls(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance from each (x, y) point to the nearest wall segment."""
    start = sim.WALLS[None, :, 0, :]
    along = sim.WALLS[None, :, 1, :] - start
    rel = points[:, None, :] - start
    u = np.clip((rel * along).sum(-1) / (along**2).sum(-1), 0.0, 1.0)
    gap = rel - u[..., None] * along
    return np.hypot(gap[..., 0], gap[..., 1]).min(axis=1)  # type: ignore[no-any-return]


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


@pytest.fixture(scope="module")
def lap() -> dict[str, list[tuple[int, Any]]]:
    """A full lap, deserialised: topic -> [(log_ns, message)]."""
    store = sim.typestore()
    by_topic: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    for m in sim.simulate(LAP_S):
        by_topic[m.topic].append((m.log_ns, store.deserialize_cdr(m.data, m.msgtype)))
    return by_topic


def test_cast_rays_single_wall_is_exact() -> None:
    wall = np.array([[[2.0, -10.0], [2.0, 10.0]]])
    ranges = sim.cast_rays((0.0, 0.0), 0.0, [0.0, math.pi / 4, -math.pi / 4], wall, 3.5)
    np.testing.assert_allclose(
        ranges, [2.0, 2.0 * math.sqrt(2.0), 2.0 * math.sqrt(2.0)], rtol=1e-12
    )
    # yaw and origin both count: from (0.5, 1) turned 45 degrees left, the wall is 1.5*sqrt(2) away
    turned = sim.cast_rays((0.5, 1.0), math.pi / 4, [0.0], wall, 3.5)
    np.testing.assert_allclose(turned, [1.5 * math.sqrt(2.0)], rtol=1e-12)


def test_cast_rays_misses_are_inf_and_nearest_wall_wins() -> None:
    walls = np.array([[[2.0, -10.0], [2.0, 10.0]], [[1.0, -0.5], [1.0, 0.5]]])
    # backwards: nothing; 1.2 rad: the long wall is 2/cos(1.2) = 5.5 m away, past max range;
    # straight ahead: the short wall at 1 m hides the long one at 2 m
    ranges = sim.cast_rays((0.0, 0.0), 0.0, [math.pi, 1.2, 0.0], walls, 3.5)
    assert ranges[0] == math.inf
    assert ranges[1] == math.inf
    assert ranges[2] == pytest.approx(1.0, abs=1e-12)
    # a ray along a segment (parallel) never hits it
    assert sim.cast_rays((0.0, 0.0), math.pi / 2, [0.0], walls[:1] - [2.0, 0.0], 3.5)[0] == math.inf


def test_simulate_is_deterministic() -> None:
    first = list(sim.simulate(3.0))
    second = list(sim.simulate(3.0))
    assert first == second
    assert len({m.data for m in first if m.topic == "/scan"}) == 15  # the scans do change


def test_rates_order_and_stamps() -> None:
    store = sim.typestore()
    msgs = list(sim.simulate(10.0, start_ns=5_000_000_000))
    counts = Counter(m.topic for m in msgs)
    for topic, expected in [("/tf", 300), ("/odom", 300), ("/joint_states", 300), ("/scan", 50)]:
        assert abs(counts[topic] - expected) <= 1, topic
    assert counts["/tf_static"] == 1
    assert msgs[0].topic == "/tf_static"
    assert msgs[0].log_ns == 5_000_000_000
    log_times = [m.log_ns for m in msgs]
    assert log_times == sorted(log_times)
    assert log_times[-1] < 5_000_000_000 + 10_000_000_000
    types = {m.topic: m.msgtype for m in msgs}
    assert types == {spec.topic: spec.msgtype for spec in sim.TOPICS}
    for m in msgs:
        decoded: Any = store.deserialize_cdr(m.data, m.msgtype)
        headers = (
            [t.header for t in decoded.transforms]
            if m.topic in ("/tf", "/tf_static")
            else [decoded.header]
        )
        assert all(_stamp_ns(h) == m.log_ns for h in headers), m.topic


def test_static_and_wheel_frames_match_the_urdf(lap: dict[str, list[tuple[int, Any]]]) -> None:
    ((_, static),) = lap["/tf_static"]
    got = {
        (t.header.frame_id, t.child_frame_id): t.transform.translation for t in static.transforms
    }
    assert set(got) == {("base_footprint", "base_link"), ("base_link", "base_scan")}
    scan_offset = got[("base_link", "base_scan")]
    assert (scan_offset.x, scan_offset.y, scan_offset.z) == pytest.approx((-0.032, 0.0, 0.172))
    assert got[("base_footprint", "base_link")].z == pytest.approx(0.010)

    _, tf = lap["/tf"][400]
    _, joints = lap["/joint_states"][400]
    frames = {t.child_frame_id: t for t in tf.transforms}
    assert frames["base_footprint"].header.frame_id == "odom"
    assert list(joints.name) == ["wheel_left_joint", "wheel_right_joint"]
    for child, y, angle in zip(
        ("wheel_left_link", "wheel_right_link"), (0.08, -0.08), joints.position, strict=True
    ):
        t = frames[child].transform
        assert frames[child].header.frame_id == "base_link"
        assert (t.translation.x, t.translation.y, t.translation.z) == pytest.approx((0.0, y, 0.023))
        # the wheel's spin axis (its z) points to the robot's left; it turns by the joint angle
        q = np.array([t.rotation.x, t.rotation.y, t.rotation.z])
        w = t.rotation.w
        x_axis = (
            (w * w - q @ q) * np.array([1.0, 0, 0])
            + 2 * q[0] * q
            + 2 * w * np.cross(q, [1.0, 0, 0])
        )
        z_axis = (
            (w * w - q @ q) * np.array([0, 0, 1.0])
            + 2 * q[2] * q
            + 2 * w * np.cross(q, [0, 0, 1.0])
        )
        np.testing.assert_allclose(z_axis, [0.0, math.sin(1.57), math.cos(1.57)], atol=1e-12)
        roll = sim.WHEEL_ROLL
        spin = math.atan2(x_axis[1] * math.cos(roll) + x_axis[2] * math.sin(roll), x_axis[0])
        assert math.remainder(spin - angle, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_demo_bag_reads_back(tmp_path: Path, storage: Literal["mcap", "sqlite3"]) -> None:
    expected = Counter(m.topic for m in sim.simulate(2.0))
    path = sim.write_demo_bag(tmp_path / "demo", 2.0, storage=storage)
    with AnyReader([path], default_typestore=sim.typestore()) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            spec.topic: spec.msgtype for spec in sim.TOPICS
        }
        durability = {}
        for c in reader.connections:
            assert isinstance(c.ext, ConnectionExtRosbag2)
            durability[c.topic] = c.ext.offered_qos_profiles[0].durability
        assert durability.pop("/tf_static") is QosDurability.TRANSIENT_LOCAL
        assert set(durability.values()) == {QosDurability.VOLATILE}
        read: Counter[str] = Counter()
        for conn, log_ns, raw in reader.messages():
            msg: Any = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/scan":
                assert len(msg.ranges) == 360
                assert _stamp_ns(msg.header) == log_ns
            read[conn.topic] += 1
        assert read == expected
    with pytest.raises(InputError, match="exists already"):
        sim.write_demo_bag(path, 1.0, storage=storage)


def test_every_scan_hit_lies_on_a_wall(lap: dict[str, list[tuple[int, Any]]]) -> None:
    ((_, static),) = lap["/tf_static"]
    offset = next(
        t.transform.translation for t in static.transforms if t.child_frame_id == "base_scan"
    )
    poses = {log_ns: odom.pose.pose for log_ns, odom in lap["/odom"]}
    hits = []
    for log_ns, scan in lap["/scan"]:
        pose = poses[log_ns]
        yaw = _yaw(pose.orientation)
        c, s = math.cos(yaw), math.sin(yaw)
        origin = np.array(
            [
                pose.position.x + c * offset.x - s * offset.y,
                pose.position.y + s * offset.x + c * offset.y,
            ]
        )
        ranges = np.asarray(scan.ranges, dtype=np.float64)
        assert scan.range_min == pytest.approx(0.12)
        assert scan.range_max == pytest.approx(3.5)
        assert scan.angle_increment == pytest.approx(2 * math.pi / 360)
        assert np.all(scan.intensities == scan.intensities[0])
        assert np.all(np.isinf(ranges) | ((ranges >= 0.12) & (ranges <= 3.5)))
        angles = yaw + scan.angle_min + np.arange(len(ranges)) * scan.angle_increment
        ok = np.isfinite(ranges)
        hits.append(
            origin + ranges[ok, None] * np.stack([np.cos(angles[ok]), np.sin(angles[ok])], -1)
        )
    points = np.concatenate(hits)
    assert len(points) > 0.5 * 360 * len(lap["/scan"])  # most rays hit something
    assert _distance_to_walls(points).max() < 0.01
    x0, y0, x1, y1 = sim.BOUNDS
    assert np.all((points >= [x0 - 0.01, y0 - 0.01]) & (points <= [x1 + 0.01, y1 + 0.01]))


def test_trajectory_stays_clear_of_walls_and_visits_every_room(
    lap: dict[str, list[tuple[int, Any]]],
) -> None:
    xy = np.array([(o.pose.pose.position.x, o.pose.pose.position.y) for _, o in lap["/odom"]])
    x0, y0, x1, y1 = sim.BOUNDS
    assert np.all((xy > [x0, y0]) & (xy < [x1, y1]))
    assert _distance_to_walls(xy).min() > 0.15
    rooms = {(bool(x > 4.0), bool(y > 3.0)) for x, y in xy}
    assert rooms == {(False, False), (True, False), (True, True), (False, True)}
    # a closed loop: after a lap the robot is back on its first leg, heading +x
    assert xy[-1, 1] == pytest.approx(1.7, abs=0.02)
    assert _yaw(lap["/odom"][-1][1].pose.pose.orientation) == pytest.approx(0.0, abs=0.02)


def test_wheels_agree_with_odometry(lap: dict[str, list[tuple[int, Any]]]) -> None:
    xy = np.array([(o.pose.pose.position.x, o.pose.pose.position.y) for _, o in lap["/odom"]])
    travelled = np.hypot(*np.diff(xy, axis=0).T).sum()
    positions = np.array([j.position for _, j in lap["/joint_states"]])
    # the last joint angle is the one taken at the last odom pose
    assert positions[-1].mean() * sim.WHEEL_RADIUS == pytest.approx(travelled, rel=0.01)
    assert travelled > 12.0
    rates = np.array([j.velocity for _, j in lap["/joint_states"]])
    v = np.array([o.twist.twist.linear.x for _, o in lap["/odom"]])
    w = np.array([o.twist.twist.angular.z for _, o in lap["/odom"]])
    np.testing.assert_allclose(rates.mean(axis=1) * sim.WHEEL_RADIUS, v, atol=1e-12)
    np.testing.assert_allclose(
        (rates[:, 1] - rates[:, 0]) * sim.WHEEL_RADIUS / sim.WHEEL_SEPARATION, w, atol=1e-12
    )
    cov = np.asarray(lap["/odom"][0][1].pose.covariance).reshape(6, 6)
    assert np.all(np.diag(cov) > 0.0)
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


def test_demo_mcap_decodes_with_the_official_mcap_reader(tmp_path: Path) -> None:
    """An independent ROS 2 CDR decoder agrees on the recorded schemas and payloads."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = sim.write_demo_bag(tmp_path / "demo", 1.0)
    (mcap_file,) = path.glob("*.mcap")
    first_scan = next(m for m in sim.simulate(1.0) if m.topic == "/scan")
    expected: Any = sim.typestore().deserialize_cdr(first_scan.data, first_scan.msgtype)
    compared = 0
    topics: Counter[str] = Counter()
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            topics[channel.topic] += 1
            assert schema is not None
            assert schema.name == next(s.msgtype for s in sim.TOPICS if s.topic == channel.topic)
            if channel.topic == "/scan" and message.log_time == first_scan.log_ns:
                np.testing.assert_array_equal(
                    np.asarray(decoded.ranges, np.float32), expected.ranges
                )
                assert decoded.header.frame_id == "base_scan"
                compared += 1
    assert compared == 1
    assert topics == Counter(m.topic for m in sim.simulate(1.0))
