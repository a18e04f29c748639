"""The robot model and its motion: the URDF agrees with the drive's kinematics, the loop
visits every room clear of the walls, wheels agree with the motion, the odometry drifts as
modelled, a fleet spreads out."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yourdfpy
from numpy.typing import NDArray

from host_bridge.demo import messages, robot, world
from tests.host_bridge.demo.support import LAP_S, Messages, track, xyz


def test_urdf_agrees_with_the_simulated_kinematics(urdf: yourdfpy.URDF) -> None:
    assert urdf.robot.name == "swanky_bot"
    joints = {j.name: j for j in urdf.robot.joints}
    links = {link.name: link for link in urdf.robot.links}
    left, right = joints["wheel_left_joint"], joints["wheel_right_joint"]
    assert left.type == right.type == "continuous"
    assert left.origin[1, 3] - right.origin[1, 3] == pytest.approx(robot.WHEEL_SEPARATION)
    for joint in (left, right):
        (visual,) = links[joint.child].visuals
        assert visual.geometry.cylinder.radius == pytest.approx(robot.WHEEL_RADIUS)
        # the axle sits one wheel radius above the floor, so the wheels touch it
        axle = urdf.get_transform(joint.child, "base_footprint")[:3, 3]
        assert axle[2] == pytest.approx(robot.WHEEL_RADIUS)
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
    np.testing.assert_allclose(scan, np.add(robot.SCAN_XYZ, (0, 0, robot.BASE_LINK_Z)), atol=1e-12)


def test_trajectory_stays_clear_of_walls_and_visits_every_room(lap: Messages) -> None:
    truth = track(lap, messages.GROUND_TRUTH_POSE_TOPIC)
    xy = truth[:, :2]
    x0, y0, x1, y1 = world.BOUNDS
    assert np.all((xy > [x0, y0]) & (xy < [x1, y1]))
    assert world.distance_to_walls(xy).min() > 0.15
    rooms = {(bool(x > 4.0), bool(y > 3.0)) for x, y in xy}
    assert rooms == {(False, False), (True, False), (True, True), (False, True)}
    # a closed loop: after a lap the robot is back on its first leg, heading +x
    assert xy[-1, 1] == pytest.approx(1.7, abs=0.02)
    assert truth[-1, 2] == pytest.approx(0.0, abs=0.02)


def test_wheels_agree_with_the_motion_and_odometry_reads_them_long(lap: Messages) -> None:
    steps = np.hypot(*np.diff(track(lap, messages.GROUND_TRUTH_POSE_TOPIC)[:, :2], axis=0).T)
    travelled = steps.sum()
    positions = np.array([j.position for _, j in lap["/joint_states"]])
    # joint angle = distance rolled / wheel radius; the last one is taken at the last pose
    assert positions[-1].mean() * robot.WHEEL_RADIUS == pytest.approx(travelled, rel=0.01)
    assert travelled > 12.0
    # the odometry reads every step, and its speed, 5 % long
    odom_steps = np.hypot(*np.diff(track(lap, "/odom")[:, :2], axis=0).T)
    np.testing.assert_allclose(odom_steps, 1.05 * steps, rtol=1e-9, atol=1e-12)
    rates = np.array([j.velocity for _, j in lap["/joint_states"]])
    v = np.array([o.twist.twist.linear.x for _, o in lap["/odom"]])
    w = np.array([o.twist.twist.angular.z for _, o in lap["/odom"]])
    np.testing.assert_allclose(1.05 * rates.mean(axis=1) * robot.WHEEL_RADIUS, v, atol=1e-12)
    np.testing.assert_allclose(
        (rates[:, 1] - rates[:, 0]) * robot.WHEEL_RADIUS / robot.WHEEL_SEPARATION, w, atol=1e-12
    )
    cov = np.asarray(lap["/odom"][0][1].pose.covariance).reshape(6, 6)
    assert np.all(np.diag(cov) > 0.0)
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


def test_fleet_starts_spread_along_the_loop() -> None:
    spacing = robot.lap_length() / 3
    starts = [next(robot.trajectory(1.0, i * spacing)) for i in range(3)]
    assert (starts[0].x, starts[0].y, starts[0].yaw) == (2.0, 1.7, 0.0)
    # 13.2 m / 3 = 4.4 m along: 0.4 m up the second leg, heading +y
    assert (starts[1].x, starts[1].y) == pytest.approx((6.0, 2.1))
    assert starts[1].yaw == pytest.approx(math.pi / 2)
    assert (starts[2].x, starts[2].y) == pytest.approx((3.8, 4.3))
    assert abs(starts[2].yaw) == pytest.approx(math.pi)
    assert list(messages.simulate(1.0, route_offset=spacing)) != list(messages.simulate(1.0))


def _lap_end(truth: NDArray[np.float64]) -> int:
    """The tick at which the robot, having gone round, passes its start again (its nearest point
    on the loop wraps from the end of the loop to its beginning)."""
    along = np.array([robot.nearest_leg(x, y)[1] for x, y in truth[:, :2]])
    return int(np.nonzero(np.diff(along) < -robot.lap_length() / 2)[0][0]) + 1


def test_odometry_drifts_as_modelled(lap: Messages) -> None:
    """/odom against /ground_truth/pose, both as published: the heading error is 2 degrees per
    metre driven, to the left, and the position the sum of the true steps read 5 % long and
    turned by the heading error of their moment; after one lap about 1 m and 26 degrees off."""
    truth, odom = track(lap, messages.GROUND_TRUTH_POSE_TOPIC), track(lap, "/odom")
    np.testing.assert_array_equal(odom[0], truth[0])  # odometry starts at the true pose
    steps = np.diff(truth[:, :2], axis=0)
    driven = np.concatenate([[0.0], np.cumsum(np.hypot(*steps.T))])
    heading_error = np.remainder(odom[:, 2] - truth[:, 2] + np.pi, 2 * np.pi) - np.pi
    np.testing.assert_allclose(heading_error, np.remainder(
        np.radians(2.0) * driven + np.pi, 2 * np.pi) - np.pi, atol=1e-9)
    # the closed form on the true path: p_odom(n) = p(0) + 1.05 * sum_j R(2 deg/m * s_j) dp_j
    c, s = np.cos(np.radians(2.0) * driven[:-1]), np.sin(np.radians(2.0) * driven[:-1])
    turned = np.stack([c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1]], -1)
    expected = truth[0, :2] + 1.05 * np.concatenate([[[0.0, 0.0]], np.cumsum(turned, axis=0)])
    end = _lap_end(truth)
    assert end / robot.TICK_HZ == pytest.approx(58.6, abs=0.5)
    assert np.linalg.norm(odom[end, :2] - expected[end]) < 0.01
    np.testing.assert_allclose(odom[:, :2], expected, atol=1e-9)  # every tick, not only the lap's
    # how far off that is: what the host's SLAM has to take out
    assert driven[end] == pytest.approx(12.85, abs=0.05)
    assert np.degrees(heading_error[end]) == pytest.approx(25.7, abs=0.1)
    assert np.linalg.norm(odom[end, :2] - truth[end, :2]) == pytest.approx(1.01, abs=0.01)


def test_odometry_track_is_what_odom_and_tf_publish(lap: Messages) -> None:
    """One source of truth: /odom, /tf's odom -> base_footprint and /ground_truth/pose are
    odometry_track's poses, tick for tick."""
    pairs = list(robot.odometry_track(LAP_S))
    assert len(pairs) == len(lap["/odom"]) == len(lap["/tf"])
    np.testing.assert_allclose(
        track(lap, "/odom"), [(o.x, o.y, o.yaw) for _, o in pairs], atol=1e-12)
    np.testing.assert_allclose(
        track(lap, messages.GROUND_TRUTH_POSE_TOPIC), [(t.x, t.y, t.yaw) for t, _ in pairs],
        atol=1e-12)
    body = [next(t for t in tf.transforms if t.child_frame_id == "base_footprint")
            for _, tf in lap["/tf"]]
    assert {t.header.frame_id for t in body} == {"odom"}
    for (_, odom), transform in zip(lap["/odom"], body, strict=True):
        pose, moved = odom.pose.pose, transform.transform
        assert xyz(moved.translation) == xyz(pose.position)
        assert (*xyz(moved.rotation), moved.rotation.w) == (*xyz(pose.orientation), pose.orientation.w)
    assert list(robot.odometry_track(LAP_S)) == pairs  # deterministic
