"""Wall extraction on a 4000x4000 synthetic floor plan, against bare Canny + HoughLinesP.

The baseline is one ``cv2.Canny`` + ``cv2.HoughLinesP`` call on the same map's wall image, the
edge detector the walls were found with before (with OpenCV doing all of it in C++); the ratio
shows what ``wall_items`` (wall mask, axis runs + Hough on the rest, merge, corners, mesh, the
Rerun archetype, the digest) costs against it. Then each step of ``wall_items`` alone (medians):
the wall mask, the detection (``detect_segments``), the merge, corner joining, the box mesh +
``rr.Mesh3D`` and the digest that skips an unchanged map; and the case the per-tile cache is
for: the same map with one cell changed, converted by a topic that converted the map before.
Run: ``.venv/bin/python benchmarks/walls_4000.py``.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import rerun as rr
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters import walls
from host_bridge.converters.occupancy import grid_from_msg
from host_bridge.converters.segments import (
    TileCache,
    detect_segments,
    join_corners,
    merge_segments,
    occupied_mask,
    segments_to_mesh,
)
from host_bridge.core.contract import ConvertContext
from host_bridge.core.options import GridOptions
from host_bridge.core.state import RobotState, TopicState

SIZE = 4000
RESOLUTION = 0.05
ROOM = 100  # cells: 5 m rooms
DOOR = 18  # cells: 0.9 m doors
REPEATS = 5


def floor_plan(rng: np.random.Generator) -> npt.NDArray[np.int8]:
    """Rooms on a 5 m pitch with two-cell walls, doors, diagonal walls and sensor noise."""
    cells = np.full((SIZE, SIZE), -1, dtype=np.int8)
    inner = slice(ROOM // 2, SIZE - ROOM // 2)
    cells[inner, inner] = 0
    lines = np.arange(ROOM // 2, SIZE - ROOM // 2 + 1, ROOM)
    for offset in (0, 1):
        cells[lines[:, None] + offset, inner] = 100
        cells[inner, lines[None, :] + offset] = 100
    # One door per room side of every inner wall line, at a random place along it.
    starts = lines[:-1]
    door_at = starts + rng.integers(10, ROOM - DOOR - 10, size=(lines.size - 2, starts.size))
    across = lines[1:-1, None, None, None] + np.array([0, 1])[None, None, :, None]
    along = door_at[:, :, None, None] + np.arange(DOOR)
    cells[across, along] = 0
    cells[along, across] = 0
    mask = np.zeros((SIZE, SIZE), dtype=np.uint8)
    for k in range(0, starts.size - 1, 3):
        x0, y0 = int(starts[k]) + 20, int(starts[k + 1]) + 20
        cv2.line(mask, (x0, y0), (x0 + 60, y0 + int(60 * math.tan(math.radians(37)))), 255, 2)
    cells[mask > 0] = 100
    noise = rng.random((SIZE, SIZE)) < 0.001
    cells[noise & (cells == 0)] = 100
    return cells


def median_time(fn: Callable[[], object]) -> float:
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def grid_message(cells: npt.NDArray[np.int8]) -> Any:
    store = get_typestore(Stores.ROS2_HUMBLE)
    t = store.types
    return t["nav_msgs/msg/OccupancyGrid"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="map"
        ),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
            resolution=RESOLUTION,
            width=SIZE,
            height=SIZE,
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=-100.0, y=-100.0, z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        ),
        data=cells.ravel(),
    )


def context(tiles: dict[bytes, Any] | None = None) -> ConvertContext:
    """A fresh robot state (the digest would skip an unchanged map), the topic's tile cache
    holding ``tiles``."""
    topic_state = TopicState()
    topic_state.state(TileCache).tiles = dict(tiles or {})
    return ConvertContext(
        robot="bench", topic="/map", entity_path="/bench/map", times={},
        topic_state=topic_state, robot_state=RobotState(),
    )


def main() -> None:
    cells = floor_plan(np.random.default_rng(7))
    msg = grid_message(cells)
    image = occupied_mask(cells) * np.uint8(255)

    def baseline() -> npt.NDArray[Any] | None:
        edges = cv2.Canny(image, 150.0, 250.0, L2gradient=True)
        lines: npt.NDArray[Any] | None = cv2.HoughLinesP(
            edges, 1.0, math.pi / 180.0, 8, minLineLength=4.0, maxLineGap=2.0
        )
        return lines

    segments = walls.wall_segments(
        grid_from_msg(msg, context()), walls.WallOptions.from_options(GridOptions(), RESOLUTION, "/map")
    )
    raw = baseline()
    base_s = median_time(baseline)
    full_s = median_time(lambda: walls.wall_items(msg, context()))
    print(
        f"map {SIZE}x{SIZE} cells at {RESOLUTION} m: baseline finds "
        f"{0 if raw is None else len(raw)} raw segments, wall_items {segments.shape[0]} walls"
    )
    print(f"baseline cv2.Canny + cv2.HoughLinesP: {base_s * 1e3:8.1f} ms")
    print(f"walls.wall_items (mask, runs, Hough, merge, mesh, digest): {full_s * 1e3:8.1f} ms")
    print(f"ratio wall_items / baseline: {full_s / base_s:.2f}")

    # One cell of one tile changed: a speck in a room of the tile at rows/cols 1024..1535.
    first = context()
    walls.wall_items(msg, first)
    before = dict(first.topic_state.state(TileCache).tiles)
    changed = cells.copy()
    changed[1300, 1290] = 100
    changed_msg = grid_message(changed)
    again = context(before)
    walls.wall_items(changed_msg, again)
    redone = len(set(again.topic_state.state(TileCache).tiles) - set(before))
    changed_s = median_time(lambda: walls.wall_items(changed_msg, context(before)))
    print(
        f"walls.wall_items, one cell changed, tile cache of the map before "
        f"({redone} of {len(before)} tiles searched again): {changed_s * 1e3:8.1f} ms"
    )
    print(f"ratio changed map / baseline: {changed_s / base_s:.2f}")
    step_times(msg, context())


def step_times(msg: Any, ctx: ConvertContext) -> None:
    """Median time of each step of ``wall_items``, run one after the other on their own."""
    grid = grid_from_msg(msg, ctx)
    options = walls.WallOptions.from_options(GridOptions(), grid.resolution, grid.topic)
    res = grid.resolution
    settings = options.detector(res)
    mask = occupied_mask(grid.cells, options.occupied_threshold)
    pixels = detect_segments(mask, settings, anchor=walls.tile_anchor(grid))
    merged = merge_segments((pixels + 0.5) * res, angle_deg=options.merge_angle_deg,
                            distance=options.merge_distance, gap=options.merge_gap,
                            min_length=options.min_length)
    joined = join_corners(merged, reach=options.join_reach)

    def mesh() -> rr.Mesh3D:
        boxes = segments_to_mesh(joined, grid.translation, grid.quaternion, options.height,
                                 options.thickness)
        return rr.Mesh3D(vertex_positions=boxes.vertices, triangle_indices=boxes.triangles,
                         vertex_normals=boxes.normals, albedo_factor=options.color)

    steps: dict[str, Callable[[], object]] = {
        "wall mask": lambda: occupied_mask(grid.cells, options.occupied_threshold),
        f"axis runs + Hough ({pixels.shape[0]} pieces)": lambda: detect_segments(
            mask, settings, anchor=walls.tile_anchor(grid)),
        f"merge ({merged.shape[0]} walls)": lambda: merge_segments(
            (pixels + 0.5) * res, angle_deg=options.merge_angle_deg,
            distance=options.merge_distance, gap=options.merge_gap, min_length=options.min_length),
        "join corners": lambda: join_corners(merged, reach=options.join_reach),
        "box mesh + rr.Mesh3D": mesh,
        "digest of the cells": lambda: walls.grid_digest(grid, options),
    }
    for label, step in steps.items():
        print(f"  step {label:<40} {median_time(step) * 1e3:8.1f} ms", flush=True)


if __name__ == "__main__":
    main()
