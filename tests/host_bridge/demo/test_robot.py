"""The robot model and its motion: the URDF agrees with the drive's kinematics, the loop
visits every room clear of the walls, wheels agree with odometry, a fleet spreads out."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yourdfpy

from host_bridge.demo import messages, robot, world
from tests.host_bridge.demo.support import Messages, yaw_of


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
    xy = np.array([(o.pose.pose.position.x, o.pose.pose.position.y) for _, o in lap["/odom"]])
    x0, y0, x1, y1 = world.BOUNDS
    assert np.all((xy > [x0, y0]) & (xy < [x1, y1]))
    assert world.distance_to_walls(xy).min() > 0.15
    rooms = {(bool(x > 4.0), bool(y > 3.0)) for x, y in xy}
    assert rooms == {(False, False), (True, False), (True, True), (False, True)}
    # a closed loop: after a lap the robot is back on its first leg, heading +x
    assert xy[-1, 1] == pytest.approx(1.7, abs=0.02)
    assert yaw_of(lap["/odom"][-1][1].pose.pose.orientation) == pytest.approx(0.0, abs=0.02)


def test_wheels_agree_with_odometry(lap: Messages) -> None:
    xy = np.array([(o.pose.pose.position.x, o.pose.pose.position.y) for _, o in lap["/odom"]])
    travelled = np.hypot(*np.diff(xy, axis=0).T).sum()
    positions = np.array([j.position for _, j in lap["/joint_states"]])
    # joint angle = distance rolled / wheel radius; the last one is taken at the last pose
    assert positions[-1].mean() * robot.WHEEL_RADIUS == pytest.approx(travelled, rel=0.01)
    assert travelled > 12.0
    rates = np.array([j.velocity for _, j in lap["/joint_states"]])
    v = np.array([o.twist.twist.linear.x for _, o in lap["/odom"]])
    w = np.array([o.twist.twist.angular.z for _, o in lap["/odom"]])
    np.testing.assert_allclose(rates.mean(axis=1) * robot.WHEEL_RADIUS, v, atol=1e-12)
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
