"""The simulated robot: exact ray casting, rates, determinism, a readable bag, and sensors (scan,
camera, depth, cloud, map, IMU, battery, logs) that agree with the world geometry, the URDF and
each other."""

from __future__ import annotations

import io
import math
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pytest
import yourdfpy
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.interfaces import ConnectionExtRosbag2, QosDurability

from host_bridge import sim
from host_bridge.errors import InputError

LAP_S = 65.0  # one full lap of the loop takes about 62 s
LAP_TOPICS = ("/tf_static", "/tf", "/odom", "/joint_states", "/scan")
SHORT_S = 6.0
LATCHED = {"/tf_static", "/robot_description", "/map"}

Messages = dict[str, list[tuple[int, Any]]]


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _log_stamp_ns(log: Any) -> int:
    """rcl_interfaces/Log has its stamp at the top, not in a header."""
    return int(log.stamp.sec) * 1_000_000_000 + int(log.stamp.nanosec)


def _decoded(**kwargs: Any) -> Messages:
    store = sim.typestore()
    by_topic: Messages = defaultdict(list)
    for m in sim.simulate(**kwargs):
        by_topic[m.topic].append((m.log_ns, store.deserialize_cdr(m.data, m.msgtype)))
    return by_topic


@pytest.fixture(scope="module")
def lap() -> Messages:
    """A full lap of the motion topics, deserialised: topic -> [(log_ns, message)]."""
    return _decoded(duration_s=LAP_S, topics=LAP_TOPICS)


@pytest.fixture(scope="module")
def short() -> Messages:
    """Every topic over a few seconds."""
    return _decoded(duration_s=SHORT_S)


@pytest.fixture(scope="module")
def urdf() -> yourdfpy.URDF:
    """The published robot model, read by an independent URDF parser."""
    return yourdfpy.URDF.load(io.StringIO(sim.robot_description()), load_meshes=False)


def _state(x: float, y: float, yaw: float) -> sim.RobotState:
    return sim.RobotState(x, y, yaw, 0.0, 0.0, (0.0, 0.0))


def _pose_at(odom: Messages, log_ns: int) -> sim.RobotState:
    pose = next(o.pose.pose for t, o in odom["/odom"] if t == log_ns)
    return _state(pose.position.x, pose.position.y, _yaw(pose.orientation))


# -- geometry ----------------------------------------------------------------------------------


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
    _, index = sim.ray_hits((0.0, 0.0), [math.pi, 0.0], walls, 3.5)
    assert index.tolist() == [-1, 1]
    # a ray along a segment (parallel) never hits it
    assert sim.cast_rays((0.0, 0.0), math.pi / 2, [0.0], walls[:1] - [2.0, 0.0], 3.5)[0] == math.inf


# -- determinism, rates, the bag ---------------------------------------------------------------


def test_simulate_is_deterministic() -> None:
    first = list(sim.simulate(3.0))
    second = list(sim.simulate(3.0))
    assert first == second
    assert {m.topic for m in first} == {spec.topic for spec in sim.TOPICS}
    assert len({m.data for m in first if m.topic == "/scan"}) == 15  # the scans do change
    assert len({m.data for m in first if m.topic == "/camera/image_raw"}) == 15
    # a topic subset is the same bytes as the full run's messages of those topics
    subset = list(sim.simulate(3.0, topics={"/map", "/odom"}))
    assert subset == [m for m in first if m.topic in ("/map", "/odom")]


def test_rates_order_and_stamps() -> None:
    store = sim.typestore()
    msgs = list(sim.simulate(10.0, start_ns=5_000_000_000))
    counts = Counter(m.topic for m in msgs)
    for topic in ("/tf", "/odom", "/joint_states", "/imu", sim.STEP_TIMER_TOPIC):
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
    assert types == {spec.topic: spec.msgtype for spec in sim.TOPICS}
    for m in msgs:
        decoded: Any = store.deserialize_cdr(m.data, m.msgtype)
        if m.topic in ("/tf", "/tf_static"):
            stamps = [_stamp_ns(t.header) for t in decoded.transforms]
        elif m.topic == "/rosout":
            stamps = [_log_stamp_ns(decoded)]
        elif hasattr(decoded, "header"):
            stamps = [_stamp_ns(decoded.header)]
        else:  # std_msgs String / Float32 have no stamp
            continue
        assert stamps, m.topic
        assert all(s == m.log_ns for s in stamps), m.topic


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
        assert {t for t, d in durability.items() if d is QosDurability.TRANSIENT_LOCAL} == LATCHED
        assert {d for t, d in durability.items() if t not in LATCHED} == {QosDurability.VOLATILE}
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


def test_demo_mcap_decodes_with_the_official_mcap_reader(tmp_path: Path) -> None:
    """An independent ROS 2 CDR decoder agrees on the recorded schemas and payloads."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = sim.write_demo_bag(tmp_path / "demo", 1.0)
    (mcap_file,) = path.glob("*.mcap")
    firsts: dict[str, sim.SimMessage] = {}
    for m in sim.simulate(1.0):
        firsts.setdefault(m.topic, m)
    store = sim.typestore()
    expected_scan: Any = store.deserialize_cdr(firsts["/scan"].data, "sensor_msgs/msg/LaserScan")
    expected_cloud = firsts["/camera/depth/points"]
    compared = 0
    topics: Counter[str] = Counter()
    with mcap_file.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            topics[channel.topic] += 1
            assert schema is not None
            assert schema.name == next(s.msgtype for s in sim.TOPICS if s.topic == channel.topic)
            if message.log_time != firsts[channel.topic].log_ns:
                continue
            if channel.topic == "/scan":
                np.testing.assert_array_equal(
                    np.asarray(decoded.ranges, np.float32), expected_scan.ranges
                )
                assert decoded.header.frame_id == "base_scan"
                compared += 1
            elif channel.topic == "/camera/depth/points":
                assert [f.name for f in decoded.fields] == ["x", "y", "z", "rgb"]
                expected: Any = store.deserialize_cdr(expected_cloud.data, expected_cloud.msgtype)
                assert bytes(decoded.data) == bytes(expected.data)
                compared += 1
            elif channel.topic == "/robot_description":
                assert decoded.data == sim.robot_description()
                compared += 1
    assert compared == 3
    assert topics == Counter(m.topic for m in sim.simulate(1.0))


# -- the robot model ---------------------------------------------------------------------------


def test_urdf_agrees_with_the_simulated_kinematics(urdf: yourdfpy.URDF) -> None:
    assert urdf.robot.name == "swanky_bot"
    joints = {j.name: j for j in urdf.robot.joints}
    links = {link.name: link for link in urdf.robot.links}
    left, right = joints["wheel_left_joint"], joints["wheel_right_joint"]
    assert left.type == right.type == "continuous"
    assert left.origin[1, 3] - right.origin[1, 3] == pytest.approx(sim.WHEEL_SEPARATION)
    for joint in (left, right):
        (visual,) = links[joint.child].visuals
        assert visual.geometry.cylinder.radius == pytest.approx(sim.WHEEL_RADIUS)
        # the axle sits one wheel radius above the floor, so the wheels touch it
        axle = urdf.get_transform(joint.child, "base_footprint")[:3, 3]
        assert axle[2] == pytest.approx(sim.WHEEL_RADIUS)
        # the spin axis points to the robot's left: positive angles roll it forward
        spin_axis = urdf.get_transform(joint.child, "base_link")[:3, :3] @ joint.axis
        np.testing.assert_allclose(spin_axis, [0.0, 1.0, 0.0], atol=1e-12)
    caster = urdf.get_transform("caster_back_link", "base_footprint")[:3, 3]
    (ball,) = links["caster_back_link"].visuals
    assert caster[2] - ball.geometry.sphere.radius == pytest.approx(0.0, abs=1e-9)
    # REP 103 optical frame: z forward, x right, y down of camera_link
    optical = urdf.get_transform("camera_optical_frame", "camera_link")[:3, :3]
    np.testing.assert_allclose(optical, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    scan = urdf.get_transform("base_scan", "base_footprint")[:3, 3]
    np.testing.assert_allclose(scan, np.add(sim.SCAN_XYZ, (0, 0, sim.BASE_LINK_Z)), atol=1e-12)


def test_static_and_wheel_frames_match_the_urdf(short: Messages, urdf: yourdfpy.URDF) -> None:
    ((_, description),) = short["/robot_description"]
    assert description.data == sim.robot_description()
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


# -- motion and the laser ----------------------------------------------------------------------


def test_every_scan_hit_lies_on_a_wall(lap: Messages) -> None:
    hits = []
    for log_ns, scan in lap["/scan"]:
        state = _pose_at(lap, log_ns)
        origin = np.array(state.to_odom(sim.SCAN_XYZ))
        ranges = np.asarray(scan.ranges, dtype=np.float64)
        assert scan.range_min == pytest.approx(0.12)
        assert scan.range_max == pytest.approx(3.5)
        assert scan.angle_increment == pytest.approx(2 * math.pi / 360)
        assert np.all(scan.intensities == scan.intensities[0])
        assert np.all(np.isinf(ranges) | ((ranges >= 0.12) & (ranges <= 3.5)))
        angles = state.yaw + scan.angle_min + np.arange(len(ranges)) * scan.angle_increment
        ok = np.isfinite(ranges)
        hits.append(
            origin + ranges[ok, None] * np.stack([np.cos(angles[ok]), np.sin(angles[ok])], -1)
        )
    points = np.concatenate(hits)
    assert len(points) > 0.5 * 360 * len(lap["/scan"])  # most rays hit something
    assert sim.distance_to_walls(points).max() < 0.01
    x0, y0, x1, y1 = sim.BOUNDS
    assert np.all((points >= [x0 - 0.01, y0 - 0.01]) & (points <= [x1 + 0.01, y1 + 0.01]))


def test_trajectory_stays_clear_of_walls_and_visits_every_room(lap: Messages) -> None:
    xy = np.array([(o.pose.pose.position.x, o.pose.pose.position.y) for _, o in lap["/odom"]])
    x0, y0, x1, y1 = sim.BOUNDS
    assert np.all((xy > [x0, y0]) & (xy < [x1, y1]))
    assert sim.distance_to_walls(xy).min() > 0.15
    rooms = {(bool(x > 4.0), bool(y > 3.0)) for x, y in xy}
    assert rooms == {(False, False), (True, False), (True, True), (False, True)}
    # a closed loop: after a lap the robot is back on its first leg, heading +x
    assert xy[-1, 1] == pytest.approx(1.7, abs=0.02)
    assert _yaw(lap["/odom"][-1][1].pose.pose.orientation) == pytest.approx(0.0, abs=0.02)


def test_wheels_agree_with_odometry(lap: Messages) -> None:
    xy = np.array([(o.pose.pose.position.x, o.pose.pose.position.y) for _, o in lap["/odom"]])
    travelled = np.hypot(*np.diff(xy, axis=0).T).sum()
    positions = np.array([j.position for _, j in lap["/joint_states"]])
    # joint angle = distance rolled / wheel radius; the last one is taken at the last pose
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


def test_fleet_starts_spread_along_the_loop() -> None:
    spacing = sim.lap_length() / 3
    starts = [next(sim.trajectory(1.0, i * spacing)) for i in range(3)]
    assert (starts[0].x, starts[0].y, starts[0].yaw) == (2.0, 1.7, 0.0)
    # 13.2 m / 3 = 4.4 m along: 0.4 m up the second leg, heading +y
    assert (starts[1].x, starts[1].y) == pytest.approx((6.0, 2.1))
    assert starts[1].yaw == pytest.approx(math.pi / 2)
    assert (starts[2].x, starts[2].y) == pytest.approx((3.8, 4.3))
    assert abs(starts[2].yaw) == pytest.approx(math.pi)
    assert list(sim.simulate(1.0, route_offset=spacing)) != list(sim.simulate(1.0))


# -- the camera --------------------------------------------------------------------------------

# From (1, 1) facing +x the camera (7.8 cm ahead of the robot) looks square at the x = 4 wall
# piece below the living-room door (y 0..1.2): every pixel on it is 4 - 1.078 m deep.
KNOWN = _state(1.0, 1.0, 0.0)
WALL_DEPTH = 4.0 - 1.0 - sim.CAMERA_XYZ[0]
CAMERA_HEIGHT_M = sim.BASE_LINK_Z + sim.CAMERA_XYZ[2]


def _project(k: NDArray[np.float64], world: tuple[float, float, float]) -> tuple[float, float]:
    """Pixel of a world point seen from KNOWN: optical x right (-y), y down (-z), z forward (x)."""
    cam = np.array([1.0 + sim.CAMERA_XYZ[0], 1.0, CAMERA_HEIGHT_M])
    rel = np.asarray(world) - cam
    optical = np.array([-rel[1], -rel[2], rel[0]])
    u, v, w = k @ optical
    return u / w, v / w


def test_depth_is_the_distance_along_the_optical_axis() -> None:
    view = sim.render_camera(KNOWN)
    assert view.rgb.shape == (sim.CAMERA_HEIGHT, sim.CAMERA_WIDTH, 3)
    assert view.depth_mm.dtype == np.uint16
    columns = (np.arange(sim.CAMERA_WIDTH) - sim.CAMERA_CX) / sim.CAMERA_FOCAL
    rows = (np.arange(sim.CAMERA_HEIGHT) - sim.CAMERA_CY) / sim.CAMERA_FOCAL
    # columns whose ray meets the wall piece: y = 1 - slope * depth within [0, 1.2]
    on_wall = (1.0 - columns * WALL_DEPTH >= 0.0) & (1.0 - columns * WALL_DEPTH <= 1.2)
    assert 40 < on_wall.sum() < 100
    # rows between floor and ceiling at that depth see the wall
    heights = CAMERA_HEIGHT_M - rows * WALL_DEPTH
    wall_rows = (heights > 0.0) & (heights < sim.WALL_HEIGHT)
    patch = view.depth_mm[np.ix_(wall_rows, on_wall)].astype(np.int64)
    assert np.abs(patch - WALL_DEPTH * 1000.0).max() <= 1  # within 1 mm, everywhere on the wall
    # the other columns: cast_rays distance times cos(angle to the axis), exactly
    angles = -np.arctan(columns)
    ranges = sim.cast_rays(KNOWN.to_odom(sim.CAMERA_XYZ), 0.0, angles, sim.WALLS, 50.0)
    centre_row = int(np.argmin(np.abs(rows)))
    np.testing.assert_allclose(view.depth[centre_row], ranges * np.cos(angles), rtol=1e-12)
    # floor pixels below the wall's foot: camera height / row slope
    floor_rows = rows > CAMERA_HEIGHT_M / WALL_DEPTH
    floor = view.depth[np.ix_(floor_rows, on_wall)]
    np.testing.assert_allclose(floor, (CAMERA_HEIGHT_M / rows[floor_rows])[:, None] * np.ones(on_wall.sum()))
    assert np.all(view.depth_mm[view.depth > sim.DEPTH_MAX] == 0)
    assert view.depth_mm.max() <= sim.DEPTH_MAX * 1000


def test_camera_info_projects_world_edges_onto_the_image(short: Messages) -> None:
    (_, info), (_, image) = short["/camera/camera_info"][0], short["/camera/image_raw"][0]
    (_, depth) = short["/camera/depth/image_raw"][0]
    k = np.asarray(info.k).reshape(3, 3)
    assert (info.width, info.height) == (image.width, image.height) == (depth.width, depth.height)
    assert (info.width, info.height) == (sim.CAMERA_WIDTH, sim.CAMERA_HEIGHT)
    assert info.header.frame_id == image.header.frame_id == depth.header.frame_id
    assert image.header.frame_id == "camera_optical_frame"
    assert image.encoding == "rgb8"
    assert image.step == 3 * image.width
    assert depth.encoding == "16UC1"
    assert depth.step == 2 * depth.width
    np.testing.assert_array_equal(np.asarray(info.p).reshape(3, 4)[:, :3], k)
    assert k[0, 0] == k[1, 1] == sim.CAMERA_FOCAL
    # The jamb at (4, 1.2), 0.5 m above the lens, projects between columns 71 and 72: the
    # render shows the wall from column 72 on and looks through the door left of it.
    u, v = _project(k, (4.0, 1.2, CAMERA_HEIGHT_M + 0.5))
    assert 71.0 < u < 72.0
    view = sim.render_camera(KNOWN)
    row = round(v)
    assert view.depth_mm[row, 72] == pytest.approx(WALL_DEPTH * 1000.0, abs=1)
    assert view.depth_mm[row, 71] > WALL_DEPTH * 1000.0 + 500.0
    # that wall piece has its own colour: blue-grey, lit square on
    assert len(sim.WALL_COLORS) == len(sim.WALLS)
    assert sim.WALL_COLORS[4].tolist() == [170, 200, 215]
    r, g, b = (int(c) for c in view.rgb[row, 72])
    assert b > g > r
    assert view.rgb[row, 71].tolist() != view.rgb[row, 72].tolist()


def test_published_images_are_the_render(short: Messages) -> None:
    odom = dict(short["/odom"])
    for (log_ns, image), (_, depth) in zip(
        short["/camera/image_raw"][::7], short["/camera/depth/image_raw"][::7], strict=True
    ):
        pose = odom[log_ns].pose.pose
        view = sim.render_camera(_state(pose.position.x, pose.position.y, _yaw(pose.orientation)))
        rgb = np.frombuffer(bytes(image.data), np.uint8).reshape(image.height, image.width, 3)
        mm = np.frombuffer(bytes(depth.data), "<u2").reshape(depth.height, depth.width)
        np.testing.assert_array_equal(rgb, view.rgb)
        np.testing.assert_array_equal(mm, view.depth_mm)
        assert np.count_nonzero(mm) == mm.size  # a closed apartment: every pixel has a return
        # the nearest pixel is the floor at the bottom edge, 0.11 m * f / 59.5 px ahead
        bottom_row_floor = CAMERA_HEIGHT_M * sim.CAMERA_FOCAL / sim.CAMERA_CY
        assert mm.min() == round(bottom_row_floor * 1000.0) == 222
        assert mm.max() <= 10_000


def test_depth_cloud_is_the_depth_image_back_projected(short: Messages) -> None:
    (log_ns, cloud), (_, depth), (_, image) = (
        short["/camera/depth/points"][10], short["/camera/depth/image_raw"][10],
        short["/camera/image_raw"][10],
    )
    assert cloud.header.frame_id == "camera_optical_frame"
    assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("rgb", 12, 7, 1)
    ]
    assert (cloud.height, cloud.width, cloud.point_step) == (30, 40, 16)
    assert cloud.row_step == 16 * 40
    points = np.frombuffer(bytes(cloud.data), np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")]
    )).reshape(30, 40)
    mm = np.frombuffer(bytes(depth.data), "<u2").reshape(120, 160)
    rgb = np.frombuffer(bytes(image.data), np.uint8).reshape(120, 160, 3)
    v, u = np.mgrid[2:120:4, 2:160:4]
    z = mm[v, u] / 1000.0
    np.testing.assert_allclose(points["z"], z, rtol=1e-6)
    np.testing.assert_allclose(points["x"], (u - sim.CAMERA_CX) / sim.CAMERA_FOCAL * z, atol=1e-6)
    np.testing.assert_allclose(points["y"], (v - sim.CAMERA_CY) / sim.CAMERA_FOCAL * z, atol=1e-6)
    packed = rgb[v, u].astype(np.uint32)
    np.testing.assert_array_equal(
        points["rgb"], (packed[..., 0] << 16) | (packed[..., 1] << 8) | packed[..., 2]
    )
    # in the odom frame every point is inside the apartment, between floor and ceiling
    state = _pose_at(short, log_ns)
    cam_x, cam_y = state.to_odom(sim.CAMERA_XYZ)
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    x = cam_x + c * points["z"] + s * points["x"]
    y = cam_y + s * points["z"] - c * points["x"]
    height = CAMERA_HEIGHT_M - points["y"]
    x0, y0, x1, y1 = sim.BOUNDS
    assert np.all((x > x0 - 0.01) & (x < x1 + 0.01) & (y > y0 - 0.01) & (y < y1 + 0.01))
    assert np.all((height > -0.01) & (height < sim.WALL_HEIGHT + 0.01))


# -- the map -----------------------------------------------------------------------------------


def test_map_grows_from_the_scans(short: Messages) -> None:
    scans = dict(short["/scan"])
    maps = short["/map"]
    assert len(maps) == SHORT_S
    known_before = 0
    for log_ns, grid in maps:
        info = grid.info
        assert grid.header.frame_id == "map"
        assert info.resolution == pytest.approx(0.05)
        assert (info.origin.orientation.w, info.origin.position.z) == (1.0, 0.0)
        cells = np.asarray(grid.data, np.int8).reshape(info.height, info.width)
        assert set(np.unique(cells).tolist()) == {-1, 0, 100}
        known = int(np.count_nonzero(cells >= 0))
        assert known > known_before  # more seen every second
        known_before = known

        # The scan of the same instant: occupied where it hits, free half-way along each ray
        # (away from walls, where another ray's hit may claim the cell).
        state = _pose_at(short, log_ns)
        ranges = np.asarray(scans[log_ns].ranges, np.float64)
        origin = np.array(state.to_odom(sim.SCAN_XYZ))
        theta = state.yaw + np.arange(360) * (2 * math.pi / 360)
        direction = np.stack([np.cos(theta), np.sin(theta)], -1)
        hit = np.isfinite(ranges)

        def cell_values(points: NDArray[np.float64], info: Any = info, cells: Any = cells) -> Any:
            ox, oy = info.origin.position.x, info.origin.position.y
            col = np.floor((points[:, 0] - ox) / info.resolution).astype(int)
            row = np.floor((points[:, 1] - oy) / info.resolution).astype(int)
            return cells[row, col]

        assert np.all(cell_values(origin + ranges[hit, None] * direction[hit]) == 100)
        middle = origin + (ranges[hit, None] / 2.0) * direction[hit]
        clear = sim.distance_to_walls(middle) > 0.08
        assert clear.sum() > 100
        assert np.all(cell_values(middle[clear]) == 0)
    # the first map covers what the first scan saw; later ones grow in whole metres
    first, last = maps[0][1].info, maps[-1][1].info
    assert last.width * last.height >= first.width * first.height
    assert (last.width % 20, last.height % 20) == (0, 0)
    assert (last.origin.position.x, last.origin.position.y) == pytest.approx((-0.525, -0.525))


# -- IMU, battery, logs, timer -----------------------------------------------------------------


def test_imu_feels_gravity_turns_and_speed_changes(short: Messages) -> None:
    odom = [o for _, o in short["/odom"]]
    imu = [m for _, m in short["/imu"]]
    assert len(imu) == len(odom)
    assert imu[0].header.frame_id == "imu_link"
    v = np.array([o.twist.twist.linear.x for o in odom])
    w = np.array([o.twist.twist.angular.z for o in odom])
    acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                    for m in imu])
    np.testing.assert_allclose(acc[:, 2], 9.80665)
    np.testing.assert_allclose(acc[:, 1], v * w, atol=1e-12)
    np.testing.assert_allclose(acc[1:, 0], np.diff(v) * sim.TICK_HZ, atol=1e-9)
    assert acc[1, 0] == pytest.approx(0.5)  # starting at MAX_ACCEL
    np.testing.assert_allclose([m.angular_velocity.z for m in imu], w)
    np.testing.assert_allclose(
        [_yaw(m.orientation) for m in imu], [_yaw(o.pose.pose.orientation) for o in odom],
        atol=1e-12,
    )


def test_battery_drains_slowly(short: Messages) -> None:
    states = [m for _, m in short["/battery_state"]]
    percentage = np.array([m.percentage for m in states])
    voltage = np.array([m.voltage for m in states])
    assert np.all(np.diff(percentage) < 0) and np.all(np.diff(voltage) < 0)  # noqa: PT018
    assert percentage[0] == pytest.approx(0.97)
    assert percentage[-1] > 0.96
    assert np.all((voltage > 10.5) & (voltage < 12.6))
    assert all(m.present and m.power_supply_status == 2 for m in states)
    assert all(m.current < 0 for m in states)


def test_rosout_reports_waypoints_and_doorways() -> None:
    store = sim.typestore()
    logs: list[Any] = [
        store.deserialize_cdr(m.data, m.msgtype) for m in sim.simulate(20.0, topics={"/rosout"})
    ]
    expected = [(20, "driving the apartment loop"), (30, "camera: no calibration"),
                (30, "passing a doorway"), (20, "waypoint 1 reached")]
    assert len(logs) == len(expected)
    for m, (level, start) in zip(logs, expected, strict=True):
        assert (m.level, m.msg[: len(start)]) == (level, start)
    assert logs[3].msg.startswith("waypoint 1 reached at (6.0, 1.7)")
    assert all(m.name == "swanky_bot.driver" for m in logs)
    # the doorway warning comes as the robot passes x = 4 at about 0.22 m/s
    seconds = [(_log_stamp_ns(m) - sim.DEFAULT_START_NS) / 1e9 for m in logs]
    assert seconds[:2] == pytest.approx([0.0, 1.0 / sim.TICK_HZ])  # one line per tick
    assert 7.0 < seconds[2] < 8.5


def test_step_timer_is_a_positive_series(short: Messages) -> None:
    values = np.array([m.data for _, m in short[sim.STEP_TIMER_TOPIC]])
    assert len(values) == SHORT_S * sim.TICK_HZ
    assert np.all((values > 0.5) & (values < 8.0))
    # camera ticks cost more than plain control ticks
    assert values[::6].mean() > values[1::6].mean() + 2.0
