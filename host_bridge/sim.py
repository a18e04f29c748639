"""A built-in simulated robot (swanky_bot, a TurtleBot3-burger-sized differential drive) driving
laps through a walled apartment.

It gives the bridge, its tests and its demos a robot without ROS, Gazebo or a recorded bag: the
messages are real CDR from the ROS 2 Humble definitions, with the frames, rates and QoS a real
robot offers, and everything is a pure function of time and start position (no randomness, no
clock), so two runs give the same bytes. The world is a list of 2D wall segments of one height;
the robot follows a closed loop with pure pursuit, and every sensor is exact geometry against
those segments (the laser and the camera cast rays, the map is built from the scans), so a test
can check each value against the geometry that produced it.

The robot model is the project's own URDF (``host_bridge/data/swanky_bot.urdf``, primitives
only): it is published on /robot_description and its fixed joints on /tf_static, its wheel joints
on /tf, as robot_state_publisher would. Odometry is exact and the odom frame is the apartment's
frame (its origin is the apartment's corner, not the start pose), so robots started at different
places of the loop share one set of coordinates; map -> odom is the identity.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections import deque
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass
from functools import cache, cached_property
from importlib import resources
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
IntArray = NDArray[np.int64]
Xyz = tuple[float, float, float]
Xyzw = tuple[float, float, float, float]

# -- the world ---------------------------------------------------------------------------------

BOUNDS: tuple[float, float, float, float] = (0.0, 0.0, 8.0, 6.0)
"""Outer walls as (x_min, y_min, x_max, y_max) in metres, in the odom frame."""

WALL_HEIGHT = 2.4
"""Every wall, the furniture included, rises from the floor (z = 0) to the ceiling."""


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

# Wall colours of the camera image, by wall index (RGB): outer walls, inner walls, furniture.
WALL_COLORS: NDArray[np.uint8] = np.array(
    [(200, 190, 170)] * 4
    + [(170, 200, 215), (150, 185, 205), (170, 200, 215)]
    + [(215, 185, 160), (200, 165, 140), (215, 185, 160)]
    + [(120, 140, 90)] * 4
    + [(150, 95, 70)] * 4,
    dtype=np.uint8,
)

WAYPOINTS: FloatArray = np.array([(2.0, 1.7), (6.0, 1.7), (6.0, 4.3), (2.0, 4.3)])
"""Corners of the closed loop the robot follows; each leg crosses one door at its middle."""


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ray_hits(
    origin_xy: ArrayLike, theta: ArrayLike, walls: ArrayLike, max_range: float
) -> tuple[FloatArray, IntArray]:
    """Distance along each ray (absolute angle ``theta``) to the nearest segment and that
    segment's index; +inf and -1 where nothing lies within ``max_range``."""
    origin = np.asarray(origin_xy, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    segs = np.asarray(walls, dtype=np.float64).reshape(-1, 2, 2)
    d = np.stack([np.cos(theta), np.sin(theta)], axis=-1)[:, None, :]  # (R, 1, 2)
    start = segs[None, :, 0, :]  # (1, N, 2)
    along = segs[None, :, 1, :] - start
    w = start - origin
    denom = _cross(d, along)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _cross(w, along) / denom
        u = _cross(w, d) / denom
    hit = (denom != 0.0) & (t > 0.0) & (t <= max_range) & (u >= 0.0) & (u <= 1.0)
    t = np.where(hit, t, np.inf)
    index = np.argmin(t, axis=1) if segs.shape[0] else np.zeros(len(theta), dtype=np.int64)
    distance = np.take_along_axis(t, index[:, None], axis=1)[:, 0] if segs.shape[0] else t[:, 0]
    return distance, np.where(np.isfinite(distance), index, -1).astype(np.int64)


def cast_rays(
    origin_xy: ArrayLike, yaw: float, angles: ArrayLike, walls: ArrayLike, max_range: float
) -> FloatArray:
    """Distance along each ray to the nearest wall segment; +inf past ``max_range``.

    Rays leave ``origin_xy`` at ``yaw + angles``; ``walls`` is (N, 2, 2). A ray parallel to a
    segment never hits it (zero-thickness walls), a ray through an endpoint does.
    """
    theta = yaw + np.asarray(angles, dtype=np.float64)
    return ray_hits(origin_xy, np.atleast_1d(theta), walls, max_range)[0]


def distance_to_walls(points: ArrayLike) -> FloatArray:
    """Distance from each (x, y) point to the nearest wall segment."""
    xy = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    start = WALLS[None, :, 0, :]
    along = WALLS[None, :, 1, :] - start
    rel = xy[:, None, :] - start
    u = np.clip((rel * along).sum(-1) / (along**2).sum(-1), 0.0, 1.0)
    gap = rel - u[..., None] * along
    return np.hypot(gap[..., 0], gap[..., 1]).min(axis=1)  # type: ignore[no-any-return]


# -- the robot model ---------------------------------------------------------------------------

URDF_NAME = "swanky_bot.urdf"


@cache
def robot_description() -> str:
    """The URDF text, read from the installed package (works from a wheel, not only a checkout)."""
    return (resources.files("host_bridge") / "data" / URDF_NAME).read_text(encoding="utf-8")


@dataclass(frozen=True, slots=True)
class UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    xyz: Xyz
    rpy: Xyz
    axis: Xyz


def _triple(element: ET.Element | None, key: str, default: str) -> Xyz:
    x, y, z = (float(v) for v in (default if element is None else element.get(key, default)).split())
    return (x, y, z)


@cache
def urdf_joints() -> dict[str, UrdfJoint]:
    """The URDF's joints by name; the simulator places its sensors and frames from these."""
    joints = {}
    for joint in ET.fromstring(robot_description()).iter("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            msg = f"{URDF_NAME}: joint {joint.get('name')!r} lacks its parent or child link"
            raise InputError(msg)
        name = joint.get("name", "")
        joints[name] = UrdfJoint(
            name=name,
            type=joint.get("type", ""),
            parent=parent.get("link", ""),
            child=child.get("link", ""),
            xyz=_triple(joint.find("origin"), "xyz", "0 0 0"),
            rpy=_triple(joint.find("origin"), "rpy", "0 0 0"),
            axis=_triple(joint.find("axis"), "xyz", "1 0 0"),
        )
    return joints


def _rpy_quaternion(rpy: Xyz) -> Xyzw:
    """URDF rpy (fixed-axis roll, then pitch, then yaw) as a quaternion (x, y, z, w)."""
    cr, sr = math.cos(rpy[0] / 2.0), math.sin(rpy[0] / 2.0)
    cp, sp = math.cos(rpy[1] / 2.0), math.sin(rpy[1] / 2.0)
    cy, sy = math.cos(rpy[2] / 2.0), math.sin(rpy[2] / 2.0)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def _quaternion_product(a: Xyzw, b: Xyzw) -> Xyzw:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def joint_quaternion(joint: UrdfJoint, angle: float = 0.0) -> Xyzw:
    """Rotation parent -> child: the joint origin, then ``angle`` about the joint axis."""
    s = math.sin(angle / 2.0)
    spin = (joint.axis[0] * s, joint.axis[1] * s, joint.axis[2] * s, math.cos(angle / 2.0))
    return _quaternion_product(_rpy_quaternion(joint.rpy), spin)


# -- the robot ---------------------------------------------------------------------------------

WHEEL_SEPARATION = 0.160
WHEEL_RADIUS = 0.033
"""Kinematics of the drive; tests check them against the URDF's wheel joints and cylinders."""
MAP_FRAME = "map"
ODOM_FRAME = "odom"
BASE_FOOTPRINT_FRAME = "base_footprint"
BASE_LINK_FRAME = "base_link"
SCAN_FRAME = "base_scan"
IMU_FRAME = "imu_link"
CAMERA_FRAME = "camera_optical_frame"
WHEEL_JOINTS = ("wheel_left_joint", "wheel_right_joint")
BASE_LINK_Z = urdf_joints()["base_joint"].xyz[2]
SCAN_XYZ = urdf_joints()["scan_joint"].xyz
CAMERA_XYZ = urdf_joints()["camera_joint"].xyz
"""Sensor mounts on base_link, read from the URDF so frames and geometry cannot disagree."""

TICK_HZ = 30
"""Integration and /tf, /odom, /joint_states, /imu rate; every other rate divides it."""
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
DOOR_CLEARANCE = 0.6  # m; closer than this to a wall the driver logs a warning

GRAVITY = 9.80665

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

    def to_odom(self, xyz: Xyz) -> tuple[float, float]:
        """The (x, y) in odom of a point given in base_footprint."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return (self.x + c * xyz[0] - s * xyz[1], self.y + s * xyz[0] + c * xyz[1])


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


def _nearest_leg(x: float, y: float) -> tuple[int, float]:
    """Index of the leg closest to (x, y) and the arc length of the closest loop point."""
    starts, directions, lengths, cumulative, _ = _loop()
    rel = np.array([x, y]) - starts
    t = np.clip((rel * directions).sum(axis=1), 0.0, lengths)
    gap = np.hypot(*(rel - t[:, None] * directions).T)
    nearest = int(np.argmin(gap))
    return nearest, float(cumulative[nearest] + t[nearest])


def _command(x: float, y: float, yaw: float, v_prev: float) -> tuple[float, float]:
    """Pure pursuit: the arc through the lookahead point, slowed to respect the turn rate."""
    tx, ty = _loop_point(_nearest_leg(x, y)[1] + LOOKAHEAD)[0] - [x, y]
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


# -- sensors -----------------------------------------------------------------------------------

SCAN_ANGLES: FloatArray = np.arange(SCAN_RAYS, dtype=np.float64) * SCAN_INCREMENT


def scan_ranges(state: RobotState) -> NDArray[np.float32]:
    """The /scan ranges at ``state`` as published: float32, +inf for no return, -inf too close."""
    origin = state.to_odom(SCAN_XYZ)
    ranges = cast_rays(origin, state.yaw, SCAN_ANGLES, WALLS, RANGE_MAX).astype(np.float32)
    ranges[ranges < RANGE_MIN] = -np.inf  # REP 117: too close to measure
    return ranges


CAMERA_WIDTH = 160
CAMERA_HEIGHT = 120
CAMERA_FOCAL = 120.0
"""Pixels; a 67 x 53 degree field of view, square pixels."""
CAMERA_CX = (CAMERA_WIDTH - 1) / 2.0
CAMERA_CY = (CAMERA_HEIGHT - 1) / 2.0
"""Principal point on the image centre: pixel (u, v) is the ray (u - cx, v - cy, f)."""
CAMERA_HZ = 5
DEPTH_MIN = 0.1
DEPTH_MAX = 10.0
"""Depth pixels outside [DEPTH_MIN, DEPTH_MAX] metres read 0 (REP 118: no return)."""
CLOUD_STRIDE = 4
"""/camera/depth/points keeps every 4th pixel of every 4th row, from the centre of each block."""
FLOOR_TILE = 0.5  # m; a checkerboard floor makes the robot's motion visible in the image
_FLOOR_RGB = np.array([[120.0, 95.0, 70.0], [150.0, 120.0, 90.0]], dtype=np.float32)
_CEILING_RGB = np.array([235.0, 235.0, 228.0], dtype=np.float32)

# x / z and y / z of the ray through each pixel column / row, in the optical frame.
_COLUMN_SLOPES: FloatArray = (np.arange(CAMERA_WIDTH, dtype=np.float64) - CAMERA_CX) / CAMERA_FOCAL
_ROW_SLOPES: FloatArray = (np.arange(CAMERA_HEIGHT, dtype=np.float64) - CAMERA_CY) / CAMERA_FOCAL


@dataclass(frozen=True, slots=True)
class CameraView:
    """One rendered frame: ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) metres along the optical
    axis (z of the optical frame), exact for walls, floor and ceiling, and ``depth_mm`` as
    /camera/depth/image_raw publishes it."""

    rgb: NDArray[np.uint8]
    depth: FloatArray
    depth_mm: NDArray[np.uint16]


def camera_matrix() -> FloatArray:
    """K of the pinhole the renderer uses (and /camera/camera_info publishes)."""
    return np.array(
        [[CAMERA_FOCAL, 0.0, CAMERA_CX], [0.0, CAMERA_FOCAL, CAMERA_CY], [0.0, 0.0, 1.0]]
    )


def render_camera(state: RobotState) -> CameraView:
    """Ray-cast one image: a ray per column against the walls, then per row whichever of the
    wall, the floor or the ceiling the pixel's ray meets first."""
    ox, oy = state.to_odom(CAMERA_XYZ)
    height = BASE_LINK_Z + CAMERA_XYZ[2]
    left_angles = -np.arctan(_COLUMN_SLOPES)  # image x points right, yaw turns left
    distance, wall = ray_hits((ox, oy), state.yaw + left_angles, WALLS, math.inf)
    wall_z = distance * np.cos(left_angles)  # (W,): depth of the wall seen by each column
    rows = _ROW_SLOPES
    with np.errstate(divide="ignore"):
        plane_z = np.where(
            rows > 0.0, height / rows, np.where(rows < 0.0, (height - WALL_HEIGHT) / rows, np.inf)
        )  # (H,): depth at which each row meets the floor (below centre) or the ceiling
    depth = np.minimum(wall_z[None, :], plane_z[:, None])
    is_wall = wall_z[None, :] <= plane_z[:, None]

    # Walls: their colour, lit by how squarely the ray meets them; floor: checker tiles where
    # the pixel's ray meets it; ceiling: plain; everything darker with distance (a depth cue).
    along = WALLS[wall, 1] - WALLS[wall, 0]
    facing = np.abs(np.sin(state.yaw + left_angles - np.arctan2(along[:, 1], along[:, 0])))
    wall_rgb = WALL_COLORS[np.maximum(wall, 0)] * (0.45 + 0.55 * facing)[:, None]  # (W, 3)
    below = rows > 0.0  # rows whose rays go down meet the floor, the others the ceiling
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    floor_z = depth[below]
    tile_x = np.floor((ox + floor_z * (c + _COLUMN_SLOPES * s)) / FLOOR_TILE)
    tile_y = np.floor((oy + floor_z * (s - _COLUMN_SLOPES * c)) / FLOOR_TILE)
    planes = np.empty((CAMERA_HEIGHT, CAMERA_WIDTH, 3), dtype=np.float32)
    planes[below] = _FLOOR_RGB[((tile_x + tile_y) % 2.0).astype(np.intp)]
    planes[~below] = _CEILING_RGB
    surface = np.where(is_wall[..., None], wall_rgb.astype(np.float32)[None, :, :], planes)
    fog = (1.0 / (1.0 + 0.06 * depth)).astype(np.float32)
    rgb = (surface * fog[..., None] + np.float32(0.5)).astype(np.uint8)  # colours stay <= 235
    return CameraView(rgb=rgb, depth=depth, depth_mm=depth_millimetres(depth))


def depth_millimetres(depth: FloatArray) -> NDArray[np.uint16]:
    """REP 118 16UC1: millimetres, 0 where the camera has no return."""
    valid = (depth >= DEPTH_MIN) & (depth <= DEPTH_MAX)
    return np.where(valid, np.rint(depth * 1000.0), 0.0).astype(np.uint16)


MAP_RESOLUTION = 0.05
MAP_HZ = 1
# One lattice for every map message; its origin is offset by half a cell so each wall (all on
# multiples of 5 cm) runs through cell centres and scan hits never fall on a cell border.
_MAP_ORIGIN = (BOUNDS[0] - 0.525, BOUNDS[1] - 0.525)
_MAP_SHAPE = (
    round((BOUNDS[3] - BOUNDS[1] + 1.05) / MAP_RESOLUTION),
    round((BOUNDS[2] - BOUNDS[0] + 1.05) / MAP_RESOLUTION),
)
MAP_GROWTH_CELLS = 20
"""The published grid grows in 1 m blocks to cover what has been seen, as SLAM maps do."""
_RAY_STEPS: FloatArray = np.arange(0.0, RANGE_MAX, MAP_RESOLUTION / 2.0)


@dataclass(frozen=True, slots=True)
class MapSnapshot:
    """A published map: occupancy values (row 0 at the origin) and the origin's (x, y)."""

    cells: NDArray[np.int8]
    origin: tuple[float, float]


class Mapper:
    """Occupancy from scans: cells a ray crosses are free, cells it ends in are occupied
    (occupied wins over free, since walls never move), everything else unknown."""

    def __init__(self) -> None:
        self.free = np.zeros(_MAP_SHAPE, dtype=bool)
        self.hit = np.zeros(_MAP_SHAPE, dtype=bool)

    @staticmethod
    def cell(xy: FloatArray) -> tuple[IntArray, IntArray]:
        """(row, column) of points (..., 2) on the lattice."""
        col = np.floor((xy[..., 0] - _MAP_ORIGIN[0]) / MAP_RESOLUTION).astype(np.int64)
        row = np.floor((xy[..., 1] - _MAP_ORIGIN[1]) / MAP_RESOLUTION).astype(np.int64)
        return row, col

    def add_scan(self, state: RobotState, ranges: NDArray[np.float32]) -> None:
        ox, oy = state.to_odom(SCAN_XYZ)
        theta = state.yaw + SCAN_ANGLES
        cos, sin = np.cos(theta), np.sin(theta)
        r = ranges.astype(np.float64)
        hits = np.isfinite(r)
        self.hit[self.cell(np.stack([ox + r[hits] * cos[hits], oy + r[hits] * sin[hits]], -1))] = True
        # Samples every half cell along each measured ray, stopping a cell short of its hit.
        free_up_to = np.where(hits, r - MAP_RESOLUTION, np.where(r == -np.inf, 0.0, RANGE_MAX))
        steps = np.nonzero(_RAY_STEPS[None, :] < free_up_to[:, None])
        d = _RAY_STEPS[steps[1]]
        ray = steps[0]
        self.free[self.cell(np.stack([ox + d * cos[ray], oy + d * sin[ray]], -1))] = True

    def snapshot(self) -> MapSnapshot:
        cells = np.where(self.hit, 100, np.where(self.free, 0, -1)).astype(np.int8)
        rows, cols = np.nonzero(self.hit | self.free)
        g = MAP_GROWTH_CELLS
        r0, c0 = (rows.min() // g) * g, (cols.min() // g) * g
        r1, c1 = min((rows.max() // g + 1) * g, _MAP_SHAPE[0]), min((cols.max() // g + 1) * g, _MAP_SHAPE[1])
        origin = (_MAP_ORIGIN[0] + c0 * MAP_RESOLUTION, _MAP_ORIGIN[1] + r0 * MAP_RESOLUTION)
        return MapSnapshot(cells=cells[r0:r1, c0:c1], origin=origin)


BATTERY_FULL_V = 12.6
BATTERY_EMPTY_V = 10.5
BATTERY_CAPACITY_AH = 1.8
_IDLE_DRAIN = 2.0e-4  # fraction per second with the robot standing
_DRIVE_DRAIN = 2.5e-3  # fraction per metre driven


def battery_fraction(state: RobotState, elapsed_s: float, start: float = 0.97) -> float:
    """Charge left: a little per second awake, more per metre driven (the wheels' travel)."""
    driven = abs(sum(state.wheel_angles)) / 2.0 * WHEEL_RADIUS
    return max(0.0, start - _IDLE_DRAIN * elapsed_s - _DRIVE_DRAIN * driven)


# rcl_interfaces/msg/Log levels
LOG_INFO = 20
LOG_WARN = 30
LOGGER_NAME = "swanky_bot.driver"


@dataclass(frozen=True, slots=True)
class LogLine:
    level: int
    text: str
    function: str


class Step:
    """What the message builders see at one tick. Sensors are computed when a builder first
    asks (a run limited to some topics skips the camera), so builders ask only on their ticks;
    ``map`` adds this tick's scan to the robot's map, so it is asked once per map tick."""

    def __init__(
        self, tick: int, stamp_ns: int, state: RobotState, *, acceleration: float,
        log: LogLine | None, mapper: Mapper,
    ) -> None:
        self.tick = tick
        self.stamp_ns = stamp_ns
        self.state = state
        self.acceleration = acceleration  # dv/dt over the last tick, m/s^2
        self.log = log
        self._mapper = mapper

    @cached_property
    def scan(self) -> NDArray[np.float32]:
        return scan_ranges(self.state)

    @cached_property
    def camera(self) -> CameraView:
        return render_camera(self.state)

    @cached_property
    def map(self) -> MapSnapshot:
        # Like slam_toolbox, which adds a scan only after some travel: one scan per map.
        self._mapper.add_scan(self.state, self.scan)
        return self._mapper.snapshot()

    @property
    def step_ms(self) -> float:
        """The /instrumentation/timer series: a modelled cost of the step (control, plus each
        sensor due), not a measured one, so that the bag stays byte-for-byte deterministic."""
        sensors = ((SCAN_HZ, 0.9), (CAMERA_HZ, 2.6), (MAP_HZ, 1.7))  # (rate, ms when due)
        due = sum(ms for hz, ms in sensors if self.tick % (TICK_HZ // hz) == 0)
        return 0.8 + 0.1 * math.sin(0.7 * self.tick) + due


class Robot:
    """The memory one simulated robot needs between ticks: its map, the leg it is on, whether
    it is in a doorway, log lines not yet published (one per tick, as a real /rosout would
    interleave them)."""

    def __init__(self) -> None:
        self.mapper = Mapper()
        self.leg: int | None = None
        self.in_doorway = False
        self.previous_v = 0.0
        self.pending: deque[LogLine] = deque()

    def _events(self, state: RobotState) -> None:
        leg = _nearest_leg(state.x, state.y)[0]
        if self.leg is None:
            self.pending.append(LogLine(
                LOG_INFO,
                f"driving the apartment loop from ({state.x:.2f}, {state.y:.2f}), next "
                f"waypoint {(leg + 1) % len(WAYPOINTS)} at {_waypoint_text(leg + 1)}",
                "start",
            ))
            self.pending.append(LogLine(
                LOG_WARN,
                "camera: no calibration file found, publishing the nominal intrinsics "
                f"(fx = fy = {CAMERA_FOCAL:g} px)",
                "start",
            ))
        elif leg != self.leg:
            self.pending.append(LogLine(
                LOG_INFO,
                f"waypoint {leg} reached at {_waypoint_text(leg)}, heading for waypoint "
                f"{(leg + 1) % len(WAYPOINTS)} at {_waypoint_text(leg + 1)}",
                "follow_loop",
            ))
        self.leg = leg
        clearance = float(distance_to_walls([(state.x, state.y)])[0])
        if clearance < DOOR_CLEARANCE and not self.in_doorway:
            self.pending.append(LogLine(
                LOG_WARN, f"passing a doorway: {clearance:.2f} m from the wall", "follow_loop"
            ))
        self.in_doorway = clearance < DOOR_CLEARANCE

    def step(self, tick: int, stamp_ns: int, state: RobotState) -> Step:
        self._events(state)
        acceleration = (state.v - self.previous_v) * TICK_HZ
        self.previous_v = state.v
        log = self.pending.popleft() if self.pending else None
        return Step(tick, stamp_ns, state, acceleration=acceleration, log=log, mapper=self.mapper)


def _waypoint_text(index: int) -> str:
    x, y = WAYPOINTS[index % len(WAYPOINTS)]
    return f"({x:.1f}, {y:.1f})"


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

    def time(self, stamp_ns: int) -> Any:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self.t["std_msgs/msg/Header"](stamp=self.time(stamp_ns), frame_id=frame_id)

    def vector(self, xyz: Xyz) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2])

    def quaternion(self, xyzw: Xyzw) -> Any:
        x, y, z, w = xyzw
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)

    def pose(self, xyz: Xyz, xyzw: Xyzw = (0.0, 0.0, 0.0, 1.0)) -> Any:
        position = self.t["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2])
        return self.t["geometry_msgs/msg/Pose"](position=position, orientation=self.quaternion(xyzw))

    def transform(
        self,
        stamp_ns: int,
        parent: str,
        child: str,
        xyz: Xyz,
        xyzw: Xyzw = (0.0, 0.0, 0.0, 1.0),
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

    def image(self, stamp_ns: int, frame_id: str, encoding: str, pixels: NDArray[Any]) -> Any:
        height, width = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).reshape(-1).view(np.uint8)
        return self.t["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, frame_id),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=len(data) // height,
            data=data,
        )


def _yaw_quaternion(yaw: float) -> Xyzw:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def _build_tf_static(b: MessageBuilder, step: Step) -> Any:
    fixed = [
        b.transform(step.stamp_ns, j.parent, j.child, j.xyz, joint_quaternion(j))
        for j in urdf_joints().values()
        if j.type == "fixed"
    ]
    return b.tf([b.transform(step.stamp_ns, MAP_FRAME, ODOM_FRAME, (0.0, 0.0, 0.0)), *fixed])


def _build_robot_description(b: MessageBuilder, _step: Step) -> Any:
    return b.t["std_msgs/msg/String"](data=robot_description())


def _build_tf(b: MessageBuilder, step: Step) -> Any:
    state = step.state
    body = b.transform(
        step.stamp_ns, ODOM_FRAME, BASE_FOOTPRINT_FRAME, (state.x, state.y, 0.0),
        _yaw_quaternion(state.yaw),
    )
    joints = urdf_joints()
    wheels = [
        b.transform(step.stamp_ns, j.parent, j.child, j.xyz, joint_quaternion(j, angle))
        for j, angle in zip((joints[n] for n in WHEEL_JOINTS), state.wheel_angles, strict=True)
    ]
    return b.tf([body, *wheels])


def _build_odom(b: MessageBuilder, step: Step) -> Any:
    t, state = b.t, step.state
    twist = t["geometry_msgs/msg/Twist"](
        linear=b.vector((state.v, 0.0, 0.0)), angular=b.vector((0.0, 0.0, state.w))
    )
    return t["nav_msgs/msg/Odometry"](
        header=b.header(step.stamp_ns, ODOM_FRAME),
        child_frame_id=BASE_FOOTPRINT_FRAME,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=b.pose((state.x, state.y, 0.0), _yaw_quaternion(state.yaw)), covariance=_COVARIANCE
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=_COVARIANCE),
    )


def _build_joint_states(b: MessageBuilder, step: Step) -> Any:
    return b.t["sensor_msgs/msg/JointState"](
        header=b.header(step.stamp_ns, BASE_LINK_FRAME),
        name=list(WHEEL_JOINTS),
        position=np.array(step.state.wheel_angles, dtype=np.float64),
        velocity=np.array(step.state.wheel_rates, dtype=np.float64),
        effort=np.zeros(0, dtype=np.float64),
    )


_IMU_COVARIANCE = np.diag([1e-4, 1e-4, 1e-4]).ravel()


def _build_imu(b: MessageBuilder, step: Step) -> Any:
    """imu_link sits on the rotation axis, aligned with base_link: the body feels the speed
    change ahead, the centripetal v*w to the left and gravity's reaction up."""
    state = step.state
    return b.t["sensor_msgs/msg/Imu"](
        header=b.header(step.stamp_ns, IMU_FRAME),
        orientation=b.quaternion(_yaw_quaternion(state.yaw)),
        orientation_covariance=_IMU_COVARIANCE,
        angular_velocity=b.vector((0.0, 0.0, state.w)),
        angular_velocity_covariance=_IMU_COVARIANCE,
        linear_acceleration=b.vector((step.acceleration, state.v * state.w, GRAVITY)),
        linear_acceleration_covariance=_IMU_COVARIANCE,
    )


def _build_scan(b: MessageBuilder, step: Step) -> Any:
    return b.t["sensor_msgs/msg/LaserScan"](
        header=b.header(step.stamp_ns, SCAN_FRAME),
        angle_min=0.0,
        angle_max=float(SCAN_ANGLES[-1]),
        angle_increment=SCAN_INCREMENT,
        # All rays are cast from one pose, so there is no per-ray delay for a consumer to undo.
        time_increment=0.0,
        scan_time=1.0 / SCAN_HZ,
        range_min=RANGE_MIN,
        range_max=RANGE_MAX,
        ranges=step.scan,
        intensities=np.full(SCAN_RAYS, SCAN_INTENSITY, dtype=np.float32),
    )


def _build_image(b: MessageBuilder, step: Step) -> Any:
    return b.image(step.stamp_ns, CAMERA_FRAME, "rgb8", step.camera.rgb)


def _build_depth(b: MessageBuilder, step: Step) -> Any:
    return b.image(step.stamp_ns, CAMERA_FRAME, "16UC1", step.camera.depth_mm)


def _build_camera_info(b: MessageBuilder, step: Step) -> Any:
    k = camera_matrix()
    return b.t["sensor_msgs/msg/CameraInfo"](
        header=b.header(step.stamp_ns, CAMERA_FRAME),
        height=CAMERA_HEIGHT,
        width=CAMERA_WIDTH,
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=k.ravel(),
        r=np.eye(3).ravel(),
        p=np.hstack([k, np.zeros((3, 1))]).ravel(),
        binning_x=0,
        binning_y=0,
        roi=b.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


_CLOUD_FIELDS = ("x", "y", "z", "rgb")
_CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def depth_cloud(view: CameraView) -> NDArray[np.void]:
    """The organised, subsampled cloud of /camera/depth/points: xyz in the optical frame from
    the published (millimetre) depth, NaN where it has no return, colour packed as PCL does
    (0x00RRGGBB in a word declared FLOAT32)."""
    half = CLOUD_STRIDE // 2
    rows = slice(half, None, CLOUD_STRIDE)
    cols = slice(half, None, CLOUD_STRIDE)
    z = view.depth_mm[rows, cols].astype(np.float64) / 1000.0
    z[z == 0.0] = np.nan
    rgb = view.rgb[rows, cols].astype(np.uint32)
    cloud = np.empty(z.shape, dtype=_CLOUD_DTYPE)
    cloud["x"] = _COLUMN_SLOPES[cols][None, :] * z
    cloud["y"] = _ROW_SLOPES[rows][:, None] * z
    cloud["z"] = z
    cloud["rgb"] = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    return cloud


def _build_points(b: MessageBuilder, step: Step) -> Any:
    cloud = depth_cloud(step.camera)
    point = b.t["sensor_msgs/msg/PointField"]
    return b.t["sensor_msgs/msg/PointCloud2"](
        header=b.header(step.stamp_ns, CAMERA_FRAME),
        height=cloud.shape[0],
        width=cloud.shape[1],
        fields=[
            point(name=name, offset=4 * index, datatype=_FLOAT32, count=1)
            for index, name in enumerate(_CLOUD_FIELDS)
        ],
        is_bigendian=False,
        point_step=_CLOUD_DTYPE.itemsize,
        row_step=_CLOUD_DTYPE.itemsize * cloud.shape[1],
        data=cloud.reshape(-1).view(np.uint8),
        is_dense=bool(np.isfinite(cloud["z"]).all()),
    )


def _build_map(b: MessageBuilder, step: Step) -> Any:
    height, width = step.map.cells.shape
    info = b.t["nav_msgs/msg/MapMetaData"](
        map_load_time=b.time(step.stamp_ns),
        resolution=MAP_RESOLUTION,
        width=width,
        height=height,
        origin=b.pose((*step.map.origin, 0.0)),
    )
    return b.t["nav_msgs/msg/OccupancyGrid"](
        header=b.header(step.stamp_ns, MAP_FRAME), info=info, data=step.map.cells.reshape(-1)
    )


POWER_SUPPLY_STATUS_DISCHARGING = 2
POWER_SUPPLY_HEALTH_GOOD = 1
POWER_SUPPLY_TECHNOLOGY_LIPO = 4


def _build_battery(b: MessageBuilder, step: Step) -> Any:
    elapsed = step.tick / TICK_HZ
    fraction = battery_fraction(step.state, elapsed)
    return b.t["sensor_msgs/msg/BatteryState"](
        header=b.header(step.stamp_ns, BASE_LINK_FRAME),
        voltage=BATTERY_EMPTY_V + (BATTERY_FULL_V - BATTERY_EMPTY_V) * fraction,
        temperature=28.0 + 2.0 * (1.0 - fraction),
        current=-(0.35 + 1.2 * abs(step.state.v)),  # negative: discharging
        charge=BATTERY_CAPACITY_AH * fraction,
        capacity=BATTERY_CAPACITY_AH,
        design_capacity=BATTERY_CAPACITY_AH,
        percentage=fraction,
        power_supply_status=POWER_SUPPLY_STATUS_DISCHARGING,
        power_supply_health=POWER_SUPPLY_HEALTH_GOOD,
        power_supply_technology=POWER_SUPPLY_TECHNOLOGY_LIPO,
        present=True,
        cell_voltage=np.zeros(0, dtype=np.float32),
        cell_temperature=np.zeros(0, dtype=np.float32),
        location="base",
        serial_number="SIM-0001",
    )


def _build_rosout(b: MessageBuilder, step: Step) -> Any:
    line = step.log
    assert line is not None
    return b.t["rcl_interfaces/msg/Log"](
        stamp=b.time(step.stamp_ns),
        level=line.level,
        name=LOGGER_NAME,
        msg=line.text,
        file="host_bridge/sim.py",
        function=line.function,
        line=0,
    )


def _build_step_timer(b: MessageBuilder, step: Step) -> Any:
    return b.t["std_msgs/msg/Float32"](data=step.step_ms)


def _always(_step: Step) -> bool:
    return True


@dataclass(frozen=True, slots=True)
class TopicSpec:
    """One simulated topic: published on the ticks where ``due`` holds, every ``every`` ticks,
    or once at the start if ``every`` is None; ``latched`` topics are offered transient_local."""

    topic: str
    msgtype: str
    every: int | None
    build: Callable[[MessageBuilder, Step], Any]
    latched: bool = False
    due: Callable[[Step], bool] = _always


_SCAN_EVERY = TICK_HZ // SCAN_HZ
_CAMERA_EVERY = TICK_HZ // CAMERA_HZ
STEP_TIMER_TOPIC = "/instrumentation/timer/sim_step"

TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec("/tf_static", "tf2_msgs/msg/TFMessage", None, _build_tf_static, latched=True),
    TopicSpec("/robot_description", "std_msgs/msg/String", None, _build_robot_description,
              latched=True),
    TopicSpec("/tf", "tf2_msgs/msg/TFMessage", 1, _build_tf),
    TopicSpec("/odom", "nav_msgs/msg/Odometry", 1, _build_odom),
    TopicSpec("/joint_states", "sensor_msgs/msg/JointState", 1, _build_joint_states),
    TopicSpec("/imu", "sensor_msgs/msg/Imu", 1, _build_imu),
    TopicSpec(STEP_TIMER_TOPIC, "std_msgs/msg/Float32", 1, _build_step_timer),
    TopicSpec("/scan", "sensor_msgs/msg/LaserScan", _SCAN_EVERY, _build_scan),
    TopicSpec("/camera/camera_info", "sensor_msgs/msg/CameraInfo", _CAMERA_EVERY, _build_camera_info),
    TopicSpec("/camera/image_raw", "sensor_msgs/msg/Image", _CAMERA_EVERY, _build_image),
    TopicSpec("/camera/depth/image_raw", "sensor_msgs/msg/Image", _CAMERA_EVERY, _build_depth),
    TopicSpec("/camera/depth/points", "sensor_msgs/msg/PointCloud2", _CAMERA_EVERY, _build_points),
    TopicSpec("/map", "nav_msgs/msg/OccupancyGrid", TICK_HZ // MAP_HZ, _build_map, latched=True),
    TopicSpec("/battery_state", "sensor_msgs/msg/BatteryState", TICK_HZ, _build_battery),
    TopicSpec("/rosout", "rcl_interfaces/msg/Log", 1, _build_rosout,
              due=lambda step: step.log is not None),
)


def simulate(
    duration_s: float = 20.0,
    *,
    start_ns: int = DEFAULT_START_NS,
    route_offset: float = 0.0,
    topics: Collection[str] | None = None,
) -> Iterator[SimMessage]:
    """Every message of a ``duration_s`` run in time order; header stamps equal log times.
    ``route_offset`` (metres along the loop) is where the robot starts: a fleet spreads out.
    ``topics`` limits the run to those topics (and their cost)."""
    store = typestore()
    builder = MessageBuilder(store)
    robot = Robot()
    wanted = [spec for spec in TOPICS if topics is None or spec.topic in topics]
    for tick, state in enumerate(trajectory(duration_s, route_offset)):
        stamp_ns = start_ns + tick * 1_000_000_000 // TICK_HZ
        step = robot.step(tick, stamp_ns, state)
        for spec in wanted:
            periodic = tick == 0 if spec.every is None else tick % spec.every == 0
            if periodic and spec.due(step):
                msg = spec.build(builder, step)
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
    route_offset: float = 0.0,
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
        for message in simulate(duration_s, route_offset=route_offset):
            writer.write(connections[message.topic], message.log_ns, message.data)
    return path
