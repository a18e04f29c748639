"""swanky_bot, a TurtleBot3-burger-sized differential drive: its model and how it drives.

The model is the project's own URDF (``swanky_bot.urdf`` beside this module, primitives only),
read with the host's URDF parser
(:func:`host_bridge.converters.urdf.kinematics.robot_kinematics`), so the frames the demo
publishes and the ones the host draws come from one reading of one file.

The robot follows the apartment's closed loop with pure pursuit; its motion is a pure function
of time and start position. Like a real robot that runs no SLAM, it has only wheel odometry,
which drifts (:data:`ODOM_SCALE_ERROR`, :data:`ODOM_HEADING_DRIFT_DEG_PER_M`), and publishes no
map -> odom: placing ``map`` is the host's SLAM's job. Odometry starts at the true start pose and
the apartment's corner is the origin of both (not the start pose), so robots started at
different places of the loop share one set of coordinates, and a SLAM map anchored at the first
odometry pose is the apartment's frame, the one :func:`odometry_track`'s true poses are in.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from functools import cache
from importlib import resources

import numpy as np

from host_bridge.converters.urdf.kinematics import robot_kinematics
from host_bridge.core.state import JointModel
from host_bridge.demo.world import WAYPOINTS, FloatArray

Xyz = tuple[float, float, float]

# -- the model ---------------------------------------------------------------------------------

URDF_NAME = "swanky_bot.urdf"


@cache
def robot_description() -> str:
    """The URDF text, read from the installed package (works from a wheel, not only a checkout)."""
    return (resources.files("host_bridge.demo") / URDF_NAME).read_text(encoding="utf-8")


@cache
def urdf_joints() -> Mapping[str, JointModel]:
    """The URDF's joints by name; the simulator places its sensors and frames from these."""
    return robot_kinematics(robot_description(), URDF_NAME).joints


def _mount(joint: str) -> Xyz:
    x, y, z = (float(v) for v in urdf_joints()[joint].translation)
    return (x, y, z)


WHEEL_SEPARATION = 0.160
WHEEL_RADIUS = 0.033
"""Kinematics of the drive; tests check them against the URDF's wheel joints and cylinders."""
MAP_FRAME = "map"
"""The apartment's frame, in which the ground truth is published (the host's SLAM map frame)."""
ODOM_FRAME = "odom"
BASE_FOOTPRINT_FRAME = "base_footprint"
BASE_LINK_FRAME = "base_link"
SCAN_FRAME = "base_scan"
IMU_FRAME = "imu_link"
CAMERA_FRAME = "camera_optical_frame"
WHEEL_JOINTS = ("wheel_left_joint", "wheel_right_joint")
BASE_LINK_Z = _mount("base_joint")[2]
SCAN_XYZ = _mount("scan_joint")
CAMERA_XYZ = _mount("camera_joint")
"""Sensor mounts on base_link, read from the URDF so frames and geometry cannot disagree."""

# -- the motion --------------------------------------------------------------------------------

TICK_HZ = 30
"""Integration and /tf, /odom, /joint_states, /imu rate; every other rate divides it."""

MAX_SPEED = 0.22  # burger's top speed, m/s
MAX_TURN_RATE = 1.5  # rad/s, below the burger's 2.84 so corners stay gentle
MAX_ACCEL = 0.5  # m/s^2; only the start needs it, pure pursuit never stops
LOOKAHEAD = 0.35  # m

ODOM_SCALE_ERROR = 0.05
"""Wheel odometry reads every distance 5 % long (a wheel radius set 5 % too large)."""
ODOM_HEADING_DRIFT_DEG_PER_M = 2.0
"""Wheel odometry's heading creeps to the left (+yaw) by 2 degrees per metre travelled (wheels
of slightly different sizes): the drift a SLAM front end has to correct."""


@dataclass(frozen=True, slots=True)
class RobotState:
    """The ground truth at one tick, in the apartment's frame; ``v``/``w`` are the command
    applied until the next tick."""

    x: float
    y: float
    yaw: float
    v: float
    w: float
    wheel_angles: tuple[float, float]  # left, right (rad)

    @property
    def wheel_rates(self) -> tuple[float, float]:
        half = self.w * WHEEL_SEPARATION / 2.0
        return ((self.v - half) / WHEEL_RADIUS, (self.v + half) / WHEEL_RADIUS)

    def to_world(self, xyz: Xyz) -> tuple[float, float]:
        """The (x, y) in the apartment's frame of a point given in base_footprint."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return (self.x + c * xyz[0] - s * xyz[1], self.y + s * xyz[0] + c * xyz[1])


@dataclass(frozen=True, slots=True)
class Pose2D:
    """A planar pose: what the wheel odometry reads, in the odom frame."""

    x: float
    y: float
    yaw: float


@cache
def _loop() -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
    """Leg starts, unit directions, lengths, arc length at each start, and the lap length."""
    along = np.roll(WAYPOINTS, -1, axis=0) - WAYPOINTS
    lengths = np.hypot(along[:, 0], along[:, 1])
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    return WAYPOINTS, along / lengths[:, None], lengths, cumulative, float(lengths.sum())


def lap_length() -> float:
    return _loop()[4]


def _loop_point(s: float) -> tuple[FloatArray, FloatArray]:
    """Point and unit direction of the loop ``s`` metres along it from the first waypoint."""
    starts, directions, _, cumulative, total = _loop()
    s %= total
    leg = int(np.searchsorted(cumulative, s, side="right")) - 1
    return starts[leg] + (s - cumulative[leg]) * directions[leg], directions[leg]


def nearest_leg(x: float, y: float) -> tuple[int, float]:
    """Index of the leg closest to (x, y) and the arc length of the closest loop point."""
    starts, directions, lengths, cumulative, _ = _loop()
    rel = np.array([x, y]) - starts
    t = np.clip((rel * directions).sum(axis=1), 0.0, lengths)
    gap = np.hypot(*(rel - t[:, None] * directions).T)
    nearest = int(np.argmin(gap))
    return nearest, float(cumulative[nearest] + t[nearest])


def _command(x: float, y: float, yaw: float, v_prev: float) -> tuple[float, float]:
    """Pure pursuit: the arc through the lookahead point, slowed to respect the turn rate."""
    tx, ty = _loop_point(nearest_leg(x, y)[1] + LOOKAHEAD)[0] - [x, y]
    lateral = -math.sin(yaw) * tx + math.cos(yaw) * ty
    curvature = 2.0 * lateral / (tx * tx + ty * ty)
    v = min(MAX_SPEED, v_prev + MAX_ACCEL / TICK_HZ)
    if abs(v * curvature) > MAX_TURN_RATE:
        v = MAX_TURN_RATE / abs(curvature)
    return v, v * curvature


def trajectory(duration_s: float, route_offset: float = 0.0) -> Iterator[RobotState]:
    """The robot's state at every tick in [0, duration_s), starting at rest on the loop
    ``route_offset`` metres after the first waypoint, heading along it."""
    dt = 1.0 / TICK_HZ
    start, heading = _loop_point(route_offset)
    x, y, yaw, v = float(start[0]), float(start[1]), math.atan2(heading[1], heading[0]), 0.0
    left = right = 0.0
    for _ in range(_tick_count(duration_s)):
        v, w = _command(x, y, yaw, v)
        state = RobotState(x, y, yaw, v, w, (left, right))
        yield state
        # Exact integration of a constant (v, w) arc, so path length equals v * dt exactly
        # and the wheel angles stay consistent with the pose.
        if abs(w) > 1e-9:
            x += v / w * (math.sin(yaw + w * dt) - math.sin(yaw))
            y -= v / w * (math.cos(yaw + w * dt) - math.cos(yaw))
        else:
            x += v * dt * math.cos(yaw)
            y += v * dt * math.sin(yaw)
        yaw = math.remainder(yaw + w * dt, 2.0 * math.pi)
        rate_left, rate_right = state.wheel_rates
        left += rate_left * dt
        right += rate_right * dt


def _tick_count(duration_s: float) -> int:
    if not (math.isfinite(duration_s) and duration_s > 0.0):
        msg = f"simulation duration must be a positive number of seconds, got {duration_s!r}"
        raise ValueError(msg)
    return math.ceil(duration_s * TICK_HZ - 1e-9)


def odometry_track(
    duration_s: float, route_offset: float = 0.0
) -> Iterator[tuple[RobotState, Pose2D]]:
    """The true state and the wheel odometry's pose at every tick of :func:`trajectory`: the one
    source of /odom and /tf (the odometry), /ground_truth/pose (the truth) and the tests.

    Odometry starts at the true pose; each tick it adds the true motion since the last tick,
    taken in the body frame, its distance read :data:`ODOM_SCALE_ERROR` long and its heading
    change :data:`ODOM_HEADING_DRIFT_DEG_PER_M` per metre to the left. So after the robot has
    driven ``s`` metres the odometry's heading is ``drift * s`` left of the truth, and its
    position is the start plus ``1 + scale error`` times the sum of the true steps, each turned
    by the heading error it was taken with. Deterministic: no noise, two runs agree bit for bit.
    """
    states = trajectory(duration_s, route_offset)
    previous = next(states)
    odom = Pose2D(previous.x, previous.y, previous.yaw)
    yield previous, odom
    for state in states:
        odom = _odometry_step(odom, previous, state)
        yield state, odom
        previous = state


def _odometry_step(odom: Pose2D, before: RobotState, after: RobotState) -> Pose2D:
    """``odom`` moved by the true step from ``before`` to ``after`` as the wheels misread it."""
    c, s = math.cos(before.yaw), math.sin(before.yaw)
    dx_world, dy_world = after.x - before.x, after.y - before.y
    dx, dy = c * dx_world + s * dy_world, -s * dx_world + c * dy_world  # in the body frame
    turn = math.remainder(after.yaw - before.yaw, 2.0 * math.pi)
    turn += math.radians(ODOM_HEADING_DRIFT_DEG_PER_M) * math.hypot(dx, dy)
    scale = 1.0 + ODOM_SCALE_ERROR
    c, s = math.cos(odom.yaw), math.sin(odom.yaw)
    return Pose2D(
        odom.x + scale * (c * dx - s * dy),
        odom.y + scale * (s * dx + c * dy),
        math.remainder(odom.yaw + turn, 2.0 * math.pi),
    )
