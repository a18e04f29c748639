"""What swanky_bot's sensors read at a given state: the lidar, the RGB-D camera (colour render,
depth, the organised cloud), the IMU and the battery.

Each reading is exact geometry against the apartment's walls (:mod:`host_bridge.demo.world`)
from the sensor's mount on the URDF, with no noise, so a test can check it against the geometry
that produced it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from host_bridge.demo.robot import BASE_LINK_Z, CAMERA_XYZ, SCAN_XYZ, WHEEL_RADIUS, RobotState, Xyz
from host_bridge.demo.world import WALL_COLORS, WALL_HEIGHT, WALLS, FloatArray, cast_rays, ray_hits

# -- the lidar ---------------------------------------------------------------------------------

SCAN_HZ = 5
SCAN_RAYS = 360
SCAN_INCREMENT = 2.0 * math.pi / SCAN_RAYS
RANGE_MIN = 0.12
RANGE_MAX = 3.5
SCAN_INTENSITY = 100.0
SCAN_ANGLES: FloatArray = np.arange(SCAN_RAYS, dtype=np.float64) * SCAN_INCREMENT


def scan_ranges(state: RobotState) -> NDArray[np.float32]:
    """The /scan ranges at ``state`` as published: float32, +inf for no return, -inf too close."""
    origin = state.to_world(SCAN_XYZ)
    ranges = cast_rays(origin, state.yaw, SCAN_ANGLES, WALLS, RANGE_MAX).astype(np.float32)
    ranges[ranges < RANGE_MIN] = -np.inf  # REP 117: too close to measure
    return ranges


# -- the camera --------------------------------------------------------------------------------

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
CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
"""A /camera/depth/points point: xyz in the optical frame, colour packed as PCL does."""
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
    ox, oy = state.to_world(CAMERA_XYZ)
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
    cloud = np.empty(z.shape, dtype=CLOUD_DTYPE)
    cloud["x"] = _COLUMN_SLOPES[cols][None, :] * z
    cloud["y"] = _ROW_SLOPES[rows][:, None] * z
    cloud["z"] = z
    cloud["rgb"] = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    return cloud


# -- the IMU and the battery -------------------------------------------------------------------

GRAVITY = 9.80665


def imu_acceleration(state: RobotState, acceleration: float) -> Xyz:
    """imu_link sits on the rotation axis, aligned with base_link: the body feels the speed
    change ``acceleration`` ahead, the centripetal v*w to the left and gravity's reaction up."""
    return (acceleration, state.v * state.w, GRAVITY)


BATTERY_FULL_V = 12.6
BATTERY_EMPTY_V = 10.5
BATTERY_CAPACITY_AH = 1.8
_IDLE_DRAIN = 2.0e-4  # fraction per second with the robot standing
_DRIVE_DRAIN = 2.5e-3  # fraction per metre driven


def battery_fraction(state: RobotState, elapsed_s: float, start: float = 0.97) -> float:
    """Charge left: a little per second awake, more per metre driven (the wheels' travel)."""
    driven = abs(sum(state.wheel_angles)) / 2.0 * WHEEL_RADIUS
    return max(0.0, start - _IDLE_DRAIN * elapsed_s - _DRIVE_DRAIN * driven)
