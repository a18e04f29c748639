"""The occupancy grid SLAM builds: log-odds per cell in sparse tiles, free space filled between
neighbouring beams, unknown kept unknown.

Cells live on one lattice anchored at the map frame's origin (cell ``(row, col)`` covers
``[col, col + 1) x [row, row + 1)`` cells), in square tiles made when a scan first reaches them,
so memory follows the area seen: a 200 m x 200 m floor at 5 cm is 3,900 tiles of 8 KiB (32
MiB) once all of it has been seen, nothing before. A cell holds its log-odds in hundredths
(int16); :data:`UNKNOWN` marks a cell no beam has crossed.

Free space of a scan is the polygon of the laser and its beams' ends (the union of the
triangles laser, end of beam i, end of beam i + 1 of neighbouring beams), drawn with OpenCV's
polygon fill on a patch around the scan: one C call per scan instead of a ray walk per beam.
Each beam's end is pulled one cell back towards the laser, so the wall a beam hit is not also
swept free by the polygon's edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from host_bridge.slam.pose import Pose2, transform_points
from host_bridge.slam.scan import Scan

TILE = 64
UNKNOWN = np.int16(-32768)
_SHIFT = 4  # fillPoly's fractional bits: vertices to 1/16 of a cell
Int8Array = npt.NDArray[np.int8]


@dataclass(frozen=True, slots=True)
class LogOdds:
    """How much one observation moves a cell, in hundredths of log-odds, and the bounds that let
    a cell change its mind again (a door opened, a person gone)."""

    hit: int = 90  # P = 0.71 per echo
    miss: int = -40  # P = 0.40 per beam through
    lowest: int = -200
    highest: int = 350


@dataclass(frozen=True, slots=True)
class DenseMap:
    """A window of the grid as ROS publishes it: occupancy in percent (0 free .. 100 occupied,
    -1 unknown), row 0 at ``origin`` (the outer corner of cell (0, 0), in metres)."""

    cells: Int8Array
    origin: tuple[float, float]
    resolution: float


class TiledGrid:
    def __init__(self, resolution: float, odds: LogOdds | None = None) -> None:
        self.resolution = resolution
        self.odds = odds or LogOdds()
        self._tiles: dict[tuple[int, int], npt.NDArray[np.int16]] = {}

    @property
    def tile_count(self) -> int:
        return len(self._tiles)

    @property
    def nbytes(self) -> int:
        return sum(tile.nbytes for tile in self._tiles.values())

    def add(self, scan: Scan, pose: Pose2) -> None:
        """Mark what ``scan``, taken with the base at ``pose`` (map frame), saw."""
        if not len(scan.ends):
            return
        res = self.resolution
        origin = transform_points(pose, scan.origin[None, :])[0] / res
        ends = transform_points(pose, scan.ends) / res
        # Free space ends one cell short of an echo (see the module docstring).
        ray = ends - origin
        length = np.hypot(ray[:, 0], ray[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            keep = np.where(scan.hit, np.maximum(length - 1.0, 0.0) / length, 1.0)
        free_ends = origin + ray * np.nan_to_num(keep)[:, None]
        everything = np.vstack([ends, origin[None, :]])
        row0, col0 = (math.floor(float(v)) - 1 for v in everything.min(axis=0)[::-1])
        row1, col1 = (math.floor(float(v)) + 2 for v in everything.max(axis=0)[::-1])
        free = np.zeros((row1 - row0, col1 - col0), np.uint8)
        # Pixel (x, y) of OpenCV is cell (col, row); a cell's centre is at its index + 0.5.
        scale = float(1 << _SHIFT)
        corner = np.array([col0 + 0.5, row0 + 0.5])
        vertices = np.rint((free_ends - corner) * scale).astype(np.int32)
        apex = np.rint((origin - corner) * scale).astype(np.int32)
        # One polygon per run of neighbouring beams: the laser, then the ends in angle order.
        # Runs share only the laser's cell, so OpenCV's even-odd fill leaves no holes.
        breaks = np.flatnonzero(~scan.adjacent) + 1
        polygons, lone = [], []
        for run in np.split(np.arange(len(vertices)), breaks):
            if len(run) > 1:
                polygons.append(np.vstack([apex[None, :], vertices[run]]))
            else:
                lone.append(vertices[run[0]])
        if polygons:
            cv2.fillPoly(free, polygons, 1, lineType=cv2.LINE_8, shift=_SHIFT)
        for vertex in lone:
            cv2.line(free, (int(apex[0]), int(apex[1])), (int(vertex[0]), int(vertex[1])), 1,
                     lineType=cv2.LINE_8, shift=_SHIFT)
        delta = free.astype(np.int16) * np.int16(self.odds.miss)
        hits = np.floor(ends[scan.hit]).astype(np.int64) - [col0, row0]
        delta[hits[:, 1], hits[:, 0]] = self.odds.hit
        seen = free.astype(bool)
        seen[hits[:, 1], hits[:, 0]] = True
        self._apply(row0, col0, delta, seen)

    def _apply(self, row0: int, col0: int, delta: npt.NDArray[np.int16],
               seen: npt.NDArray[np.bool_]) -> None:
        rows, cols = delta.shape
        for tile_row in range(row0 // TILE, (row0 + rows - 1) // TILE + 1):
            for tile_col in range(col0 // TILE, (col0 + cols - 1) // TILE + 1):
                top, left = tile_row * TILE, tile_col * TILE
                r0, r1 = max(row0, top), min(row0 + rows, top + TILE)
                c0, c1 = max(col0, left), min(col0 + cols, left + TILE)
                patch_seen = seen[r0 - row0 : r1 - row0, c0 - col0 : c1 - col0]
                if not patch_seen.any():
                    continue
                tile = self._tiles.get((tile_row, tile_col))
                if tile is None:
                    tile = self._tiles[(tile_row, tile_col)] = np.full((TILE, TILE), UNKNOWN, np.int16)
                window = tile[r0 - top : r1 - top, c0 - left : c1 - left]
                window[patch_seen & (window == UNKNOWN)] = 0
                updated = window + delta[r0 - row0 : r1 - row0, c0 - col0 : c1 - col0]
                np.clip(updated, self.odds.lowest, self.odds.highest, out=updated)
                window[patch_seen] = updated[patch_seen]

    def dense(self) -> DenseMap:
        """The smallest window holding every tile, as occupancy percent (see :class:`DenseMap`)."""
        if not self._tiles:
            return DenseMap(np.zeros((0, 0), np.int8), (0.0, 0.0), self.resolution)
        keys = np.array(list(self._tiles))
        (top, left), (bottom, right) = keys.min(axis=0), keys.max(axis=0) + 1
        odds = np.full(((bottom - top) * TILE, (right - left) * TILE), UNKNOWN, np.int16)
        for (tile_row, tile_col), tile in self._tiles.items():
            r, c = (tile_row - top) * TILE, (tile_col - left) * TILE
            odds[r : r + TILE, c : c + TILE] = tile
        known = odds != UNKNOWN
        cells = np.full(odds.shape, -1, np.int8)
        cells[known] = np.rint(100.0 / (1.0 + np.exp(-odds[known].astype(np.float32) / 100.0)))
        origin = (float(left * TILE) * self.resolution, float(top * TILE) * self.resolution)
        return DenseMap(cells, origin, self.resolution)
