"""A built-in simulated TurtleBot3 burger driving laps through a walled apartment.

It gives the bridge, its tests and its demos a robot without ROS, Gazebo or a recorded bag: the
messages are real CDR from the ROS 2 Humble definitions, with the frames, rates and QoS a real
burger offers, and everything is a pure function of time (no randomness), so two runs give the
same bytes. The world is a list of 2D wall segments; the robot follows a closed loop with pure
pursuit and the laser is exact ray casting against those segments, so a test can check every
scan point against the geometry that produced it.

Later sensors (a depth camera, a growing map) plug in as more entries of ``TOPICS``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.errors import InputError

FloatArray = NDArray[np.float64]

# -- the world ---------------------------------------------------------------------------------

BOUNDS: tuple[float, float, float, float] = (0.0, 0.0, 8.0, 6.0)
"""Outer walls as (x_min, y_min, x_max, y_max) in metres, in the odom frame."""


def _box(x0: float, y0: float, x1: float, y1: float) -> list[tuple[tuple[float, float], ...]]:
    return [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]


# Four rooms (living room bottom left, kitchen bottom right, bedroom top right, study top left)
# split by a wall at x=4 and one at y=3, each with 1 m door gaps that the loop drives through
# at their middle; two pieces of furniture give the scans something besides walls.
WALLS: FloatArray = np.array(
    [
        *_box(*BOUNDS),
        ((4.0, 0.0), (4.0, 1.2)),
        ((4.0, 2.2), (4.0, 3.8)),
        ((4.0, 4.8), (4.0, 6.0)),
        ((0.0, 3.0), (1.5, 3.0)),
        ((2.5, 3.0), (5.5, 3.0)),
        ((6.5, 3.0), (8.0, 3.0)),
        *_box(5.0, 0.3, 7.0, 0.9),  # kitchen counter
        *_box(6.9, 4.9, 7.6, 5.6),  # wardrobe
    ],
    dtype=np.float64,
)
"""Wall segments, shape (N, 2 endpoints, xy), metres in the odom frame."""

WAYPOINTS: FloatArray = np.array([(2.0, 1.7), (6.0, 1.7), (6.0, 4.3), (2.0, 4.3)])
"""Corners of the closed loop the robot follows; each leg crosses one door at its middle."""


def cast_rays(
    origin_xy: ArrayLike, yaw: float, angles: ArrayLike, walls: ArrayLike, max_range: float
) -> FloatArray:
    """Distance along each ray to the nearest wall segment; +inf past ``max_range``.

    Rays leave ``origin_xy`` at ``yaw + angles``; ``walls`` is (N, 2, 2). A ray parallel to a
    segment never hits it (zero-thickness walls), a ray through an endpoint does.
    """
    origin = np.asarray(origin_xy, dtype=np.float64)
    theta = yaw + np.asarray(angles, dtype=np.float64)
    segs = np.asarray(walls, dtype=np.float64).reshape(-1, 2, 2)
    d = np.stack([np.cos(theta), np.sin(theta)], axis=-1)[:, None, :]  # (R, 1, 2)
    start = segs[None, :, 0, :]  # (1, N, 2)
    along = segs[None, :, 1, :] - start
    w = start - origin

    def cross(a: FloatArray, b: FloatArray) -> FloatArray:
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

    denom = cross(d, along)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross(w, along) / denom
        u = cross(w, d) / denom
    hit = (denom != 0.0) & (t > 0.0) & (t <= max_range) & (u >= 0.0) & (u <= 1.0)
    return np.where(hit, t, np.inf).min(axis=1, initial=np.inf)  # type: ignore[no-any-return]


# -- the robot (TurtleBot3 burger) -------------------------------------------------------------

WHEEL_SEPARATION = 0.160
WHEEL_RADIUS = 0.033
ODOM_FRAME = "odom"
BASE_FOOTPRINT_FRAME = "base_footprint"
BASE_LINK_FRAME = "base_link"
SCAN_FRAME = "base_scan"
WHEEL_FRAMES = ("wheel_left_link", "wheel_right_link")
WHEEL_JOINTS = ("wheel_left_joint", "wheel_right_joint")

# Joint origins from turtlebot3_burger.urdf (the URDF's rpy is -1.57, not -pi/2: kept so the
# wheels sit exactly where the robot model puts them).
BASE_LINK_Z = 0.010
SCAN_XYZ = (-0.032, 0.0, 0.172)
WHEEL_XYZ = ((0.0, 0.08, 0.023), (0.0, -0.080, 0.023))
WHEEL_ROLL = -1.57

TICK_HZ = 30
"""Integration and /tf, /odom, /joint_states rate; every other rate divides it."""
SCAN_HZ = 5
SCAN_RAYS = 360
SCAN_INCREMENT = 2.0 * math.pi / SCAN_RAYS
RANGE_MIN = 0.12
RANGE_MAX = 3.5
SCAN_INTENSITY = 100.0

MAX_SPEED = 0.22  # burger's top speed, m/s
MAX_TURN_RATE = 1.5  # rad/s, below the burger's 2.84 so corners stay gentle
MAX_ACCEL = 0.5  # m/s^2; only the start needs it, pure pursuit never stops
LOOKAHEAD = 0.35  # m

# diff_drive_controller's default diagonals (x y z roll pitch yaw); constant because the
# simulated odometry is exact and nothing downstream should read a drift model into it.
_COVARIANCE = np.diag([0.001, 0.001, 0.001, 0.001, 0.001, 0.01]).ravel()

DEFAULT_START_NS = 1_700_000_000_000_000_000


@dataclass(frozen=True, slots=True)
class RobotState:
    """The ground truth at one tick; ``v``/``w`` are the command applied until the next tick."""

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


@cache
def _loop() -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
    """Leg starts, unit directions, lengths, arc length at each start, and the lap length."""
    along = np.roll(WAYPOINTS, -1, axis=0) - WAYPOINTS
    lengths = np.hypot(along[:, 0], along[:, 1])
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    return WAYPOINTS, along / lengths[:, None], lengths, cumulative, float(lengths.sum())


def _lookahead_point(x: float, y: float) -> FloatArray:
    """The loop point LOOKAHEAD further along than the loop point closest to (x, y)."""
    starts, directions, lengths, cumulative, total = _loop()
    rel = np.array([x, y]) - starts
    t = np.clip((rel * directions).sum(axis=1), 0.0, lengths)
    gap = np.hypot(*(rel - t[:, None] * directions).T)
    nearest = int(np.argmin(gap))
    s = (cumulative[nearest] + t[nearest] + LOOKAHEAD) % total
    leg = int(np.searchsorted(cumulative, s, side="right")) - 1
    point: FloatArray = starts[leg] + (s - cumulative[leg]) * directions[leg]
    return point


def _command(x: float, y: float, yaw: float, v_prev: float) -> tuple[float, float]:
    """Pure pursuit: the arc through the lookahead point, slowed to respect the turn rate."""
    tx, ty = _lookahead_point(x, y) - [x, y]
    lateral = -math.sin(yaw) * tx + math.cos(yaw) * ty
    curvature = 2.0 * lateral / (tx * tx + ty * ty)
    v = min(MAX_SPEED, v_prev + MAX_ACCEL / TICK_HZ)
    if abs(v * curvature) > MAX_TURN_RATE:
        v = MAX_TURN_RATE / abs(curvature)
    return v, v * curvature


def trajectory(duration_s: float) -> Iterator[RobotState]:
    """The robot's state at every tick in [0, duration_s), starting at rest on the first corner."""
    dt = 1.0 / TICK_HZ
    start = WAYPOINTS[0]
    heading = WAYPOINTS[1] - start
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


# -- messages ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SimMessage:
    """One serialized message as a recorder would see it."""

    topic: str
    msgtype: str
    log_ns: int
    data: bytes


@cache
def typestore() -> Typestore:
    return get_typestore(Stores.ROS2_HUMBLE)


class MessageBuilder:
    """Message constructors bound to the typestore; every stamp is the log time."""

    def __init__(self, store: Typestore) -> None:
        self.t = store.types

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return self.t["std_msgs/msg/Header"](
            stamp=self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            frame_id=frame_id,
        )

    def vector(self, xyz: tuple[float, float, float]) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2])

    def quaternion(self, xyzw: tuple[float, float, float, float]) -> Any:
        x, y, z, w = xyzw
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def transform(
        self,
        stamp_ns: int,
        parent: str,
        child: str,
        xyz: tuple[float, float, float],
        xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
    ) -> Any:
        return self.t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            transform=self.t["geometry_msgs/msg/Transform"](
                translation=self.vector(xyz), rotation=self.quaternion(xyzw)
            ),
        )

    def tf(self, transforms: list[Any]) -> Any:
        return self.t["tf2_msgs/msg/TFMessage"](transforms=transforms)


def _yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def _wheel_quaternion(angle: float) -> tuple[float, float, float, float]:
    """Rx(WHEEL_ROLL) * Rz(angle): the URDF joint origin, then the spin about the joint axis."""
    sr, cr = math.sin(WHEEL_ROLL / 2.0), math.cos(WHEEL_ROLL / 2.0)
    sa, ca = math.sin(angle / 2.0), math.cos(angle / 2.0)
    return (sr * ca, -sr * sa, cr * sa, cr * ca)


def _build_tf_static(b: MessageBuilder, _state: RobotState, stamp_ns: int) -> Any:
    return b.tf(
        [
            b.transform(stamp_ns, BASE_FOOTPRINT_FRAME, BASE_LINK_FRAME, (0.0, 0.0, BASE_LINK_Z)),
            b.transform(stamp_ns, BASE_LINK_FRAME, SCAN_FRAME, SCAN_XYZ),
        ]
    )


def _build_tf(b: MessageBuilder, state: RobotState, stamp_ns: int) -> Any:
    body = b.transform(
        stamp_ns,
        ODOM_FRAME,
        BASE_FOOTPRINT_FRAME,
        (state.x, state.y, 0.0),
        _yaw_quaternion(state.yaw),
    )
    wheels = [
        b.transform(stamp_ns, BASE_LINK_FRAME, frame, xyz, _wheel_quaternion(angle))
        for frame, xyz, angle in zip(WHEEL_FRAMES, WHEEL_XYZ, state.wheel_angles, strict=True)
    ]
    return b.tf([body, *wheels])


def _build_odom(b: MessageBuilder, state: RobotState, stamp_ns: int) -> Any:
    t = b.t
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=state.x, y=state.y, z=0.0),
        orientation=b.quaternion(_yaw_quaternion(state.yaw)),
    )
    twist = t["geometry_msgs/msg/Twist"](
        linear=b.vector((state.v, 0.0, 0.0)), angular=b.vector((0.0, 0.0, state.w))
    )
    return t["nav_msgs/msg/Odometry"](
        header=b.header(stamp_ns, ODOM_FRAME),
        child_frame_id=BASE_FOOTPRINT_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_COVARIANCE),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=_COVARIANCE),
    )


def _build_joint_states(b: MessageBuilder, state: RobotState, stamp_ns: int) -> Any:
    return b.t["sensor_msgs/msg/JointState"](
        header=b.header(stamp_ns, BASE_LINK_FRAME),
        name=list(WHEEL_JOINTS),
        position=np.array(state.wheel_angles, dtype=np.float64),
        velocity=np.array(state.wheel_rates, dtype=np.float64),
        effort=np.zeros(0, dtype=np.float64),
    )


SCAN_ANGLES: FloatArray = np.arange(SCAN_RAYS, dtype=np.float64) * SCAN_INCREMENT


def _build_scan(b: MessageBuilder, state: RobotState, stamp_ns: int) -> Any:
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    origin = (
        state.x + c * SCAN_XYZ[0] - s * SCAN_XYZ[1],
        state.y + s * SCAN_XYZ[0] + c * SCAN_XYZ[1],
    )
    ranges = cast_rays(origin, state.yaw, SCAN_ANGLES, WALLS, RANGE_MAX).astype(np.float32)
    ranges[ranges < RANGE_MIN] = -np.inf  # REP 117: too close to measure
    return b.t["sensor_msgs/msg/LaserScan"](
        header=b.header(stamp_ns, SCAN_FRAME),
        angle_min=0.0,
        angle_max=float(SCAN_ANGLES[-1]),
        angle_increment=SCAN_INCREMENT,
        # All rays are cast from one pose, so there is no per-ray delay for a consumer to undo.
        time_increment=0.0,
        scan_time=1.0 / SCAN_HZ,
        range_min=RANGE_MIN,
        range_max=RANGE_MAX,
        ranges=ranges,
        intensities=np.full(SCAN_RAYS, SCAN_INTENSITY, dtype=np.float32),
    )


@dataclass(frozen=True, slots=True)
class TopicSpec:
    """One simulated topic: published every ``every`` ticks, or once at the start if None."""

    topic: str
    msgtype: str
    every: int | None
    build: Callable[[MessageBuilder, RobotState, int], Any]

    @property
    def latched(self) -> bool:
        return self.every is None


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec("/tf_static", "tf2_msgs/msg/TFMessage", None, _build_tf_static),
    TopicSpec("/tf", "tf2_msgs/msg/TFMessage", 1, _build_tf),
    TopicSpec("/odom", "nav_msgs/msg/Odometry", 1, _build_odom),
    TopicSpec("/joint_states", "sensor_msgs/msg/JointState", 1, _build_joint_states),
    TopicSpec("/scan", "sensor_msgs/msg/LaserScan", TICK_HZ // SCAN_HZ, _build_scan),
)


def simulate(duration_s: float = 20.0, *, start_ns: int = DEFAULT_START_NS) -> Iterator[SimMessage]:
    """Every message of a ``duration_s`` run in time order; header stamps equal log times."""
    store = typestore()
    builder = MessageBuilder(store)
    for tick, state in enumerate(trajectory(duration_s)):
        stamp_ns = start_ns + tick * 1_000_000_000 // TICK_HZ
        for spec in TOPICS:
            due = tick == 0 if spec.every is None else tick % spec.every == 0
            if due:
                msg = spec.build(builder, state, stamp_ns)
                data = bytes(store.serialize_cdr(msg, spec.msgtype))
                yield SimMessage(spec.topic, spec.msgtype, stamp_ns, data)


# -- recording ---------------------------------------------------------------------------------


def _qos(durability: QosDurability) -> Qos:
    """What rosbag2 records for a reliable publisher with default deadline and liveliness."""
    infinite = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)
    return Qos(
        history=QosHistory.UNKNOWN,
        depth=0,
        reliability=QosReliability.RELIABLE,
        durability=durability,
        deadline=infinite,
        lifespan=infinite,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=infinite,
        avoid_ros_namespace_conventions=False,
    )


_STORAGE = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def write_demo_bag(
    path: Path,
    duration_s: float = 20.0,
    *,
    storage: Literal["mcap", "sqlite3"] = "mcap",
) -> Path:
    """Record ``simulate(duration_s)`` as a rosbag2 directory at ``path``; latched topics are
    offered transient_local so a relay replaying the bag caches them like a live robot's."""
    path = Path(path)
    if path.exists():
        msg = f"demo bag target {path} exists already; remove it or choose another path"
        raise InputError(msg)
    store = typestore()
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=_STORAGE[storage]) as writer:
        connections = {
            spec.topic: writer.add_connection(
                spec.topic,
                spec.msgtype,
                typestore=store,
                offered_qos_profiles=[
                    _qos(QosDurability.TRANSIENT_LOCAL if spec.latched else QosDurability.VOLATILE)
                ],
            )
            for spec in TOPICS
        }
        for message in simulate(duration_s):
            writer.write(connections[message.topic], message.log_ns, message.data)
    return path
