"""``--save-map DIR``: what SLAM built, in the files ROS tools read.

* ``DIR/<robot>/map.yaml`` + ``map.pgm``: nav2 ``map_saver_cli``'s format in its default
  ``trinary`` mode, which ``nav2_map_server`` loads: a binary (P5) PGM whose first row is the
  map's top (largest y), 254 for free cells (occupancy below ``free_thresh``), 0 for occupied
  (above ``occupied_thresh``), 205 for unknown and everything between; the YAML names the image,
  ``mode``, ``resolution``, ``origin`` (x, y, yaw of the lower-left cell's outer corner),
  ``negate``, ``occupied_thresh`` and ``free_thresh`` with map_saver's defaults.
* ``DIR/<robot>/trajectory.tum``: one line per scan, ``t x y z qx qy qz qw`` (TUM RGB-D's
  format, which ``evo`` reads): the base in the map frame, seconds since the epoch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from host_bridge.slam.grid import DenseMap

MAP_IMAGE = "map.pgm"
MAP_YAML = "map.yaml"
TRAJECTORY = "trajectory.tum"
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.25
# map_saver's trinary values.
FREE_PIXEL = 254
OCCUPIED_PIXEL = 0
UNKNOWN_PIXEL = 205


def trinary_pixels(cells: npt.NDArray[np.int8]) -> npt.NDArray[np.uint8]:
    """Occupancy percent (-1 unknown) as map_saver's trinary image, top row first."""
    pixels = np.full(cells.shape, UNKNOWN_PIXEL, np.uint8)
    known = cells >= 0
    pixels[known & (cells < FREE_THRESH * 100)] = FREE_PIXEL
    pixels[known & (cells > OCCUPIED_THRESH * 100)] = OCCUPIED_PIXEL
    return np.flipud(pixels)


def write_map(directory: Path, grid: DenseMap) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    pixels = trinary_pixels(grid.cells)
    height, width = pixels.shape
    with (directory / MAP_IMAGE).open("wb") as image:
        header = f"P5\n# CREATOR: swanky-host {grid.resolution:.3f} m/pix\n{width} {height}\n255\n"
        image.write(header.encode())
        image.write(np.ascontiguousarray(pixels).tobytes())
    x, y = grid.origin
    (directory / MAP_YAML).write_text(
        f"image: {MAP_IMAGE}\n"
        "mode: trinary\n"
        f"resolution: {grid.resolution:g}\n"
        f"origin: [{x:g}, {y:g}, 0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH:g}\n"
        f"free_thresh: {FREE_THRESH:g}\n",
        encoding="utf-8",
    )


def write_trajectory(path: Path, stamps_ns: npt.NDArray[np.int64], poses: npt.NDArray[np.float64]) -> None:
    """``poses`` (n, 3): x, y, yaw of the base in the map frame at ``stamps_ns``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    seconds, nanos = np.divmod(stamps_ns, 1_000_000_000)
    half = poses[:, 2] / 2.0
    with path.open("w", encoding="utf-8") as out:
        for sec, nsec, (x, y, _), qz, qw in zip(
            seconds.tolist(), nanos.tolist(), poses.tolist(), np.sin(half).tolist(),
            np.cos(half).tolist(), strict=True,
        ):
            # + 0.0: no "-0.000000000" for a heading of -0.
            quaternion = f"0.000000000 0.000000000 {qz + 0.0:.9f} {qw:.9f}"
            out.write(f"{sec}.{nsec:09d} {x:.6f} {y:.6f} 0.000000 {quaternion}\n")
