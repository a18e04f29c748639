"""Wall meshes from occupancy grids: wall cells -> axis runs + Hough on the rest -> merge -> boxes.

The geometry is ``host_bridge/converters/segments.py``; this module applies it to OccupancyGrid messages.

Each wall segment is extruded into a box (``wall_thickness`` x ``wall_height``) and all boxes go
out as ONE ``rr.Mesh3D`` at ``<grid entity>/walls``, in the grid's header frame with the grid's
full origin pose applied, so the boxes stand on the occupied cells of the GridMap.

Detection (:func:`~host_bridge.converters.segments.detect_segments`): the walls of a building map are
mostly axis-aligned, so wall cells bordering a non-wall cell are taken as runs along rows and
columns (a few numpy passes per 512x512 tile), the runs of one wall clustered and fitted with
one line; only the cells no run of ``hough_min_length`` holds go to HoughLinesP (diagonal
walls), and small groups of them (pillars, bumps) become boxes. A map whose walls are mostly
off the grid axes (a SLAM map whose first pose was turned) is searched turned into its
dominant direction. Each tile's findings are cached per topic under a digest of the cells its
search reads, with tiles fixed to the map's cells (:func:`tile_anchor`), so a map that grew or
changed in a few places is searched again only there.

Cost (``benchmarks/walls_4000.py``, a busy 2-core machine): 120-210 ms for a 4000x4000 floor
plan (16 M cells, 3057 walls), 0.35-0.6x one bare Canny + HoughLinesP call on the same map
(the detector before, Canny + HoughLinesP per window and edge direction, took 1.2-1.4 s);
detection about half of it, the merge 20-30 ms, the mesh 10 ms, the digest 10 ms. One changed
cell, with the topic's tile cache: 1 of 64 tiles searched again, 110-160 ms, the rest being
the merge, mesh and digests of the whole map. A 400x400 part of the plan takes 7 ms; the plan
turned 20 degrees about 0.9 s. Still too slow for the receive path, so this module offers
:data:`GRID_WALLS` and :data:`UPDATE_WALLS` (the ``slow`` converters of the registry's
OccupancyGrid and OccupancyGridUpdate rows) for the dispatcher to run in a latest-only worker
thread after ``occupancy`` has converted the same message (an update's walls are built from the grid
``occupancy`` just patched). A grid whose cells, geometry and wall options hash to what its wall
entity already shows yields no items, so a re-published static map costs one hash
(``robot_state.wall_digests``, keyed by wall entity: a grid and its updates draw the same
walls). A grid without walls yields a ``Clear`` of the wall entity.

Options (the grid topic's :class:`~host_bridge.core.options.GridOptions`, which holds the fixed
defaults; a nav2 costmap's record has none, and it no walls; lengths in metres): ``walls``
(default: on for topics whose last name part is ``map``), ``wall_height``, ``wall_thickness``
(default one cell but at least 0.05),
``wall_color`` (RGB), ``occupied_threshold`` (cell value, map_server's 65),
``merge_distance`` (default 4.5 cells but at least 0.1), ``merge_angle_deg``, ``merge_gap``
(bridges crossing walls and missing cells, not doors; runs on one line are joined across
such gaps before fitting), ``min_length``, ``join_reach`` (default 4 cells but at least 0.15),
``hough_votes``, ``hough_min_length`` (the shortest axis run and Hough line, default 4 cells),
``hough_max_gap`` (default 2 cells).
The two sides of a wall make two runs, so ``merge_distance`` must exceed the distance between
them (its thickness less one cell; the runs of a wall up to two cells thick are one cluster
already) and stay below the centre-to-centre distance of neighbouring parallel walls; half
of it is how far a run may lie from the line fitted through its cluster.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters._common import frame_components
from host_bridge.converters.occupancy import grid_for_update, grid_from_msg
from host_bridge.converters.segments import (
    DetectorSettings,
    Float64Array,
    TileCache,
    detect_segments,
    join_corners,
    merge_segments,
    occupied_mask,
    segments_to_mesh,
)
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.core.options import GridOptions, GridUpdateOptions
from host_bridge.core.state import Grid, RobotState
from host_bridge.errors import ConvertError

WALLS_CHILD = "walls"


@dataclass(frozen=True, slots=True)
class WallOptions:
    """Wall extraction settings, lengths in metres."""

    height: float
    thickness: float
    color: tuple[int, ...]
    occupied_threshold: int
    merge_distance: float
    merge_angle_deg: float
    merge_gap: float
    min_length: float
    join_reach: float
    hough_votes: int
    hough_min_length: float
    hough_max_gap: float

    @classmethod
    def from_options(cls, options: GridOptions, resolution: float, topic: str) -> WallOptions:
        """The grid topic's wall options; the lengths it leaves open follow the cell size."""

        def length(name: str, value: float) -> float:
            if not (math.isfinite(value) and value > 0.0):
                text = f"{topic}: option {name} is {value}; give a positive length in metres"
                raise ConvertError(text)
            return float(value)

        def given(value: float | None, derived: float) -> float:
            return derived if value is None else value

        angle = float(options.merge_angle_deg)
        if not 0.0 < angle < 90.0:
            text = f"{topic}: option merge_angle_deg is {angle}; give an angle in (0, 90) degrees"
            raise ConvertError(text)
        return cls(
            height=length("wall_height", options.wall_height),
            thickness=length("wall_thickness", given(options.wall_thickness, max(resolution, 0.05))),
            color=tuple(int(c) for c in options.wall_color),
            occupied_threshold=int(options.occupied_threshold),
            merge_distance=length(
                "merge_distance", given(options.merge_distance, max(0.1, 4.5 * resolution))
            ),
            merge_angle_deg=angle,
            merge_gap=length("merge_gap", options.merge_gap),
            min_length=length("min_length", options.min_length),
            join_reach=length("join_reach", given(options.join_reach, max(0.15, 4 * resolution))),
            hough_votes=int(options.hough_votes),
            hough_min_length=length("hough_min_length", given(options.hough_min_length, 4 * resolution)),
            hough_max_gap=length("hough_max_gap", given(options.hough_max_gap, 2 * resolution)),
        )

    def detector(self, resolution: float) -> DetectorSettings:
        """The detection lengths in cells of ``resolution`` metres."""
        return DetectorSettings(
            min_run=max(2, round(self.hough_min_length / resolution)),
            votes=self.hough_votes,
            max_line_gap=self.hough_max_gap / resolution,
            # Empty cells k between two runs whose ends, k + 1 cells apart, the merge would join.
            gap=max(0, math.ceil(round(self.merge_gap / resolution, 6)) - 2),
            fit_tolerance=self.merge_distance / 2.0 / resolution,
        )


def tile_anchor(grid: Grid) -> tuple[int, int]:
    """The (row, col) of the grid's first cell on the map's cell lattice: the origin position in
    cells along the grid's own axes. A SLAM map that grows moves its origin by whole cells, so
    its tiles stay on the same cells and keep their cached findings."""
    x, y, z, w = grid.quaternion.tolist()
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    tx, ty = float(grid.translation[0]), float(grid.translation[1])
    col = (math.cos(yaw) * tx + math.sin(yaw) * ty) / grid.resolution
    row = (-math.sin(yaw) * tx + math.cos(yaw) * ty) / grid.resolution
    return round(row), round(col)


def wall_segments(grid: Grid, options: WallOptions, cache: TileCache | None = None) -> Float64Array:
    """Wall segments of a grid, (M, 4) in grid-local metres (before the origin pose); ``cache``
    keeps per-tile findings for the grid's next version."""
    if grid.cells.size == 0:
        return np.zeros((0, 4), dtype=np.float64)
    res = grid.resolution
    pixels = detect_segments(
        occupied_mask(grid.cells, options.occupied_threshold),
        options.detector(res),
        anchor=tile_anchor(grid),
        cache=cache,
    )
    # Pieces are in pixel indices; a cell's centre is half a cell in from its corner.
    merged = merge_segments(
        (pixels + 0.5) * res,
        angle_deg=options.merge_angle_deg,
        distance=options.merge_distance,
        gap=options.merge_gap,
        min_length=options.min_length,
    )
    return join_corners(merged, reach=options.join_reach)


def wall_options(grid: Grid) -> GridOptions | None:
    """The grid topic's options when it has walls: a map's ``walls`` (default: on for topics
    named map); a costmap has none."""
    options = grid.options
    if not isinstance(options, GridOptions):
        return None
    walls = grid.topic.rstrip("/").rsplit("/", 1)[-1] == "map" if options.walls is None else options.walls
    return options if walls else None


def grid_digest(grid: Grid, options: WallOptions) -> bytes:
    """What the walls of ``grid`` depend on, hashed: cells, geometry, frame and wall options."""
    # SHA-1 (hardware-accelerated here) hashes the 16 MB of a 4000x4000 map in 9 ms, BLAKE2b
    # in 19-34 ms; this only tells versions of one map apart, nobody forges it.
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(grid.cells).data)
    geometry = (
        grid.cells.shape, grid.resolution, grid.translation.tolist(), grid.quaternion.tolist(),
        grid.frame, options,
    )
    h.update(repr(geometry).encode())
    return h.digest()


def grid_wall_items(grid: Grid, robot_state: RobotState, cache: TileCache) -> list[LogEntry]:
    """The wall mesh of ``grid`` (nothing when it is unchanged, a Clear when it has none)."""
    given = wall_options(grid)
    if given is None:
        return []
    options = WallOptions.from_options(given, grid.resolution, grid.topic)
    path = f"{grid.entity_path}/{WALLS_CHILD}"
    # Keyed by wall entity, not per topic: a grid and its updates draw the same walls.
    digests = robot_state.wall_digests
    digest = grid_digest(grid, options)
    if digests.get(path) == digest:
        return []
    segments = wall_segments(grid, options, cache)
    digests[path] = digest
    if segments.shape[0] == 0:
        return [LogItem(path, (rr.Clear(recursive=False),))]
    mesh = segments_to_mesh(
        segments, grid.translation, grid.quaternion, options.height, options.thickness
    )
    mesh3d = rr.Mesh3D(
        vertex_positions=mesh.vertices,
        triangle_indices=mesh.triangles,
        vertex_normals=mesh.normals,
        albedo_factor=options.color,
    )
    return [LogItem(path, (*frame_components(grid.frame), mesh3d))]


def wall_items(grid_msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    """Wall mesh of an OccupancyGrid (slow: see the module docstring for cost and threading)."""
    return grid_wall_items(
        grid_from_msg(grid_msg, ctx), ctx.robot_state, ctx.topic_state.state(TileCache)
    )


def update_wall_items(update_msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    """Walls of the grid an OccupancyGridUpdate patched (the update itself is already in it)."""
    grid = grid_for_update(ctx, ctx.options(GridUpdateOptions).grid_topic)
    return grid_wall_items(grid, ctx.robot_state, ctx.topic_state.state(TileCache))


GRID_WALLS = per_message(wall_items)
UPDATE_WALLS = per_message(update_wall_items)
