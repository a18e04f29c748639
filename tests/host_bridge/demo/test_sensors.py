"""Sensors that agree with the world geometry, the URDF and each other: scan, camera, depth,
cloud, IMU, battery; all see the true pose (/ground_truth/pose), not the drifting odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from host_bridge.demo import robot, sensors, world
from host_bridge.demo.messages import GROUND_TRUTH_POSE_TOPIC
from tests.host_bridge.demo.support import Messages, state_at, track, true_state_at, yaw_of


def test_every_scan_hit_lies_on_a_wall(lap: Messages) -> None:
    hits = []
    for log_ns, scan in lap["/scan"]:
        state = true_state_at(lap, log_ns)
        origin = np.array(state.to_world(robot.SCAN_XYZ))
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
    assert world.distance_to_walls(points).max() < 0.01
    x0, y0, x1, y1 = world.BOUNDS
    assert np.all((points >= [x0 - 0.01, y0 - 0.01]) & (points <= [x1 + 0.01, y1 + 0.01]))


# -- the camera --------------------------------------------------------------------------------


KNOWN = state_at(1.0, 1.0, 0.0)
WALL_DEPTH = 4.0 - 1.0 - robot.CAMERA_XYZ[0]
CAMERA_HEIGHT_M = robot.BASE_LINK_Z + robot.CAMERA_XYZ[2]


def _project(k: NDArray[np.float64], world: tuple[float, float, float]) -> tuple[float, float]:
    """Pixel of a world point seen from KNOWN: optical x right (-y), y down (-z), z forward (x)."""
    cam = np.array([1.0 + robot.CAMERA_XYZ[0], 1.0, CAMERA_HEIGHT_M])
    rel = np.asarray(world) - cam
    optical = np.array([-rel[1], -rel[2], rel[0]])
    u, v, w = k @ optical
    return u / w, v / w


def test_depth_is_the_distance_along_the_optical_axis() -> None:
    view = sensors.render_camera(KNOWN)
    assert view.rgb.shape == (sensors.CAMERA_HEIGHT, sensors.CAMERA_WIDTH, 3)
    assert view.depth_mm.dtype == np.uint16
    columns = (np.arange(sensors.CAMERA_WIDTH) - sensors.CAMERA_CX) / sensors.CAMERA_FOCAL
    rows = (np.arange(sensors.CAMERA_HEIGHT) - sensors.CAMERA_CY) / sensors.CAMERA_FOCAL
    # columns whose ray meets the wall piece: y = 1 - slope * depth within [0, 1.2]
    on_wall = (1.0 - columns * WALL_DEPTH >= 0.0) & (1.0 - columns * WALL_DEPTH <= 1.2)
    assert 40 < on_wall.sum() < 100
    # rows between floor and ceiling at that depth see the wall
    heights = CAMERA_HEIGHT_M - rows * WALL_DEPTH
    wall_rows = (heights > 0.0) & (heights < world.WALL_HEIGHT)
    patch = view.depth_mm[np.ix_(wall_rows, on_wall)].astype(np.int64)
    assert np.abs(patch - WALL_DEPTH * 1000.0).max() <= 1  # within 1 mm, everywhere on the wall
    # the other columns: cast_rays distance times cos(angle to the axis), exactly
    angles = -np.arctan(columns)
    ranges = world.cast_rays(KNOWN.to_world(robot.CAMERA_XYZ), 0.0, angles, world.WALLS, 50.0)
    centre_row = int(np.argmin(np.abs(rows)))
    np.testing.assert_allclose(view.depth[centre_row], ranges * np.cos(angles), rtol=1e-12)
    # floor pixels below the wall's foot: camera height / row slope
    floor_rows = rows > CAMERA_HEIGHT_M / WALL_DEPTH
    floor = view.depth[np.ix_(floor_rows, on_wall)]
    np.testing.assert_allclose(floor, (CAMERA_HEIGHT_M / rows[floor_rows])[:, None] * np.ones(on_wall.sum()))
    assert np.all(view.depth_mm[view.depth > sensors.DEPTH_MAX] == 0)
    assert view.depth_mm.max() <= sensors.DEPTH_MAX * 1000


def test_camera_info_projects_world_edges_onto_the_image(short: Messages) -> None:
    (_, info), (_, image) = short["/camera/camera_info"][0], short["/camera/image_raw"][0]
    (_, depth) = short["/camera/depth/image_raw"][0]
    k = np.asarray(info.k).reshape(3, 3)
    assert (info.width, info.height) == (image.width, image.height) == (depth.width, depth.height)
    assert (info.width, info.height) == (sensors.CAMERA_WIDTH, sensors.CAMERA_HEIGHT)
    assert info.header.frame_id == image.header.frame_id == depth.header.frame_id
    assert image.header.frame_id == "camera_optical_frame"
    assert image.encoding == "rgb8"
    assert image.step == 3 * image.width
    assert depth.encoding == "16UC1"
    assert depth.step == 2 * depth.width
    np.testing.assert_array_equal(np.asarray(info.p).reshape(3, 4)[:, :3], k)
    assert k[0, 0] == k[1, 1] == sensors.CAMERA_FOCAL
    # The jamb at (4, 1.2), 0.5 m above the lens, projects between columns 71 and 72: the
    # render shows the wall from column 72 on and looks through the door left of it.
    u, v = _project(k, (4.0, 1.2, CAMERA_HEIGHT_M + 0.5))
    assert 71.0 < u < 72.0
    view = sensors.render_camera(KNOWN)
    row = round(v)
    assert view.depth_mm[row, 72] == pytest.approx(WALL_DEPTH * 1000.0, abs=1)
    assert view.depth_mm[row, 71] > WALL_DEPTH * 1000.0 + 500.0
    # that wall piece has its own colour: blue-grey, lit square on
    assert len(world.WALL_COLORS) == len(world.WALLS)
    assert world.WALL_COLORS[4].tolist() == [170, 200, 215]
    r, g, b = (int(c) for c in view.rgb[row, 72])
    assert b > g > r
    assert view.rgb[row, 71].tolist() != view.rgb[row, 72].tolist()


def test_published_images_are_the_render(short: Messages) -> None:
    for (log_ns, image), (_, depth) in zip(
        short["/camera/image_raw"][::7], short["/camera/depth/image_raw"][::7], strict=True
    ):
        view = sensors.render_camera(true_state_at(short, log_ns))
        rgb = np.frombuffer(bytes(image.data), np.uint8).reshape(image.height, image.width, 3)
        mm = np.frombuffer(bytes(depth.data), "<u2").reshape(depth.height, depth.width)
        np.testing.assert_array_equal(rgb, view.rgb)
        np.testing.assert_array_equal(mm, view.depth_mm)
        assert np.count_nonzero(mm) == mm.size  # a closed apartment: every pixel has a return
        # the nearest pixel is the floor at the bottom edge, 0.11 m * f / 59.5 px ahead
        bottom_row_floor = CAMERA_HEIGHT_M * sensors.CAMERA_FOCAL / sensors.CAMERA_CY
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
    np.testing.assert_allclose(points["x"], (u - sensors.CAMERA_CX) / sensors.CAMERA_FOCAL * z, atol=1e-6)
    np.testing.assert_allclose(points["y"], (v - sensors.CAMERA_CY) / sensors.CAMERA_FOCAL * z, atol=1e-6)
    packed = rgb[v, u].astype(np.uint32)
    np.testing.assert_array_equal(
        points["rgb"], (packed[..., 0] << 16) | (packed[..., 1] << 8) | packed[..., 2]
    )
    # at the true pose every point is inside the apartment, between floor and ceiling
    state = true_state_at(short, log_ns)
    cam_x, cam_y = state.to_world(robot.CAMERA_XYZ)
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    x = cam_x + c * points["z"] + s * points["x"]
    y = cam_y + s * points["z"] - c * points["x"]
    height = CAMERA_HEIGHT_M - points["y"]
    x0, y0, x1, y1 = world.BOUNDS
    assert np.all((x > x0 - 0.01) & (x < x1 + 0.01) & (y > y0 - 0.01) & (y < y1 + 0.01))
    assert np.all((height > -0.01) & (height < world.WALL_HEIGHT + 0.01))


# -- IMU and battery ---------------------------------------------------------------------------


def test_imu_feels_gravity_turns_and_speed_changes(short: Messages) -> None:
    odom = [o for _, o in short["/odom"]]
    imu = [m for _, m in short["/imu"]]
    assert len(imu) == len(odom)
    assert imu[0].header.frame_id == "imu_link"
    # the IMU feels the true motion: /odom's speed is read 5 % long, its turn rate is true
    v = np.array([o.twist.twist.linear.x for o in odom]) / (1.0 + robot.ODOM_SCALE_ERROR)
    w = np.array([o.twist.twist.angular.z for o in odom])
    acc = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                    for m in imu])
    np.testing.assert_allclose(acc[:, 2], 9.80665)
    np.testing.assert_allclose(acc[:, 1], v * w, atol=1e-12)
    np.testing.assert_allclose(acc[1:, 0], np.diff(v) * robot.TICK_HZ, atol=1e-9)
    assert acc[1, 0] == pytest.approx(0.5)  # starting at MAX_ACCEL
    np.testing.assert_allclose([m.angular_velocity.z for m in imu], w)
    # its orientation is the true heading, not the odometry's drifting one
    np.testing.assert_allclose(
        [yaw_of(m.orientation) for m in imu], track(short, GROUND_TRUTH_POSE_TOPIC)[:, 2], atol=1e-12
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
