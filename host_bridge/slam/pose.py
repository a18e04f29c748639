"""Poses in the plane: (x, y, yaw) as float64 arrays, composed and inverted as SE(2) elements.

SLAM here is 2D (a planar laser on a ground robot), so every pose it keeps is three numbers;
the 4x4 matrices of :mod:`small_gicp` and the quaternions of ROS and Rerun are made from them
at the edges.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

Pose2 = npt.NDArray[np.float64]
"""(x, y, yaw): a frame's position and heading in its parent frame, metres and radians."""

IDENTITY: Pose2 = np.zeros(3)


def pose2(x: float, y: float, yaw: float) -> Pose2:
    return np.array([x, y, math.remainder(yaw, 2.0 * math.pi)])


def compose(a: Pose2, b: Pose2) -> Pose2:
    """``a`` then ``b`` (``b`` given in ``a``'s frame): T_a * T_b."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return pose2(a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def inverse(a: Pose2) -> Pose2:
    c, s = math.cos(a[2]), math.sin(a[2])
    return pose2(-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2])


def between(a: Pose2, b: Pose2) -> Pose2:
    """``b`` seen from ``a``: T_a^-1 * T_b."""
    return compose(inverse(a), b)


def transform_points(pose: Pose2, points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Points (n, 2) given in the pose's frame, in its parent frame."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rotation = np.array([[c, -s], [s, c]])
    moved: npt.NDArray[np.float64] = points @ rotation.T + pose[:2]
    return moved


def to_matrix(pose: Pose2) -> npt.NDArray[np.float64]:
    """The 4x4 homogeneous transform (z up) of a planar pose."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    matrix = np.eye(4)
    matrix[:2, :2] = [[c, -s], [s, c]]
    matrix[:2, 3] = pose[:2]
    return matrix


def from_matrix(matrix: npt.NDArray[np.float64]) -> Pose2:
    """The planar part of a 4x4 transform: its xy translation and its heading."""
    return pose2(float(matrix[0, 3]), float(matrix[1, 3]), math.atan2(matrix[1, 0], matrix[0, 0]))


def yaw_of(xyzw: npt.ArrayLike) -> float:
    """The heading of a quaternion (x, y, z, w) about z."""
    x, y, z, w = (float(v) for v in np.asarray(xyzw, dtype=np.float64))
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_of(yaw: float) -> tuple[float, float, float, float]:
    """The quaternion (x, y, z, w) of a heading about z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))
