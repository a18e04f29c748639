"""The apartment the demo robot drives through, and exact 2D geometry against its walls.

The world is a list of 2D wall segments of one height in the apartment's frame (``map``, and
``odom`` at the start); the loop the robot follows is four corners. Every sensor is exact
geometry against those segments (the laser and the camera cast rays), so a test can check each
value against the geometry that produced it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

BOUNDS: tuple[float, float, float, float] = (0.0, 0.0, 8.0, 6.0)
"""Outer walls as (x_min, y_min, x_max, y_max) in metres, in the apartment's frame."""

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
"""Wall segments, shape (N, 2 endpoints, xy), metres in the apartment's frame."""

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
