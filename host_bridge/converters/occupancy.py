"""nav_msgs/OccupancyGrid -> ``rr.GridMap``; map_msgs/OccupancyGridUpdate patches the last grid.

nav2's own grid, nav2_msgs/Costmap (``costmap_raw``: one 0..255 cost per cell, its metadata like
OccupancyGrid's info) and CostmapUpdate (Jazzy on) are drawn the same way: their costs go
through the table nav2's Costmap2DPublisher uses to publish ``costmap`` as an OccupancyGrid
(:data:`COST_TO_OCCUPANCY`), so they look as RViz shows that topic; ``color_scheme: raw`` shows
the costs themselves.

The grid travels to the viewer as one byte per cell (the int8 value, so -1 becomes 255) and the
viewer applies its own RViz palettes (``Colormap.RvizMap`` / ``RvizCostmap``) on the GPU: the
colours are RViz's (free white, occupied black, a grey ramp between, unknown grey-green; costmap
blue-to-red with lethal/inscribed highlights and free cells transparent) and a 4000x4000 map
costs one 16 MB flip-copy rather than an RGBA expansion.

Geometry: ``info.origin`` is the pose of the outer corner of cell (0, 0) in the header frame,
and that is exactly what GridMap's translation + quaternion mean for the lower-left corner of
its image. Rerun draws image row 0 at the top (far from that corner) while ROS row 0 lies at
the origin, so rows are flipped.

Options (per grid topic): ``color_scheme`` "map" | "costmap" | "raw" (default: "costmap" when
the topic name contains "costmap", else "map"; "raw" shows the byte values as grey levels),
``opacity`` and ``draw_order`` (by topic name: 1.0 and 0 for maps, 0.7 and 1 for costmaps, 0.7
and 2 for local costmaps, so costmaps layer over the map), plus, for an OccupancyGrid, the wall
options of ``walls.py``.

State: the last grid of every topic lives in ``ctx.robot_state.grids[topic]`` as an
immutable :class:`Grid`, because its updates arrive on another topic (``/costmap_updates``
patches ``/costmap``; option ``grid_topic`` overrides that naming rule). A patch builds a new
Grid instead of writing into the old one, so a worker thread may read a grid while the receive
path replaces it.

Dispatcher contract: :data:`GRID` and :data:`GRID_UPDATE` here are the fast path (a few ms even
for a large map; validation, one flip-copy). The wall meshes built from the same messages are
slow (see ``walls.py``): the registry's rows of the same two types name them as ``slow``;
the dispatcher runs those in a latest-only worker after this module's converter has handled
the same message (an update's walls read the grid this module patched).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import frame_components, xyz, xyzw
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.core.options import CostmapUpdateOptions, GridDrawingOptions, GridOptions, GridUpdateOptions
from host_bridge.core.state import Grid
from host_bridge.errors import ConvertError

UPDATES_SUFFIX = "_updates"

_COLORMAPS: dict[str, rr.components.Colormap | None] = {
    "map": rr.components.Colormap.RvizMap,
    "costmap": rr.components.Colormap.RvizCostmap,
    "raw": None,
}

# nav2_costmap_2d's cost_translation_table_: 0 free, 1..252 scaled to 1..98, 253 inscribed 99,
# 254 lethal 100, 255 unknown -1.
COST_TO_OCCUPANCY = np.array(
    [0, *(1 + (97 * (cost - 1)) // 251 for cost in range(1, 253)), 99, 100, -1], dtype=np.int8
)


def _unit_quaternion(orientation: Any, topic: str) -> npt.NDArray[np.float64]:
    q = np.array(xyzw(orientation), dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm):
        msg = f"{topic}: info.origin.orientation is not finite ({q.tolist()}); fix the map's origin"
        raise ConvertError(msg)
    return q / norm


def _grid(
    msg: Any, info: Any, size: tuple[int, int], data: npt.NDArray[np.int8], ctx: ConvertContext,
    *, options: GridDrawingOptions,
) -> Grid:
    """Validated Grid of a message with a header, ``info`` (OccupancyGrid's ``info``, Costmap's
    ``metadata``) of the ``size`` (width, height) and the cells ``data`` (not copied)."""
    field = "info" if hasattr(msg, "info") else "metadata"
    resolution = float(info.resolution)
    if not (math.isfinite(resolution) and resolution > 0.0):
        text = (
            f"{ctx.topic}: {field}.resolution is {resolution}; a grid needs a positive cell size "
            "in metres per cell (fix the map publisher's resolution parameter)"
        )
        raise ConvertError(text)
    width, height = size
    if data.size != width * height:
        text = (
            f"{ctx.topic}: data has {data.size} cells but {field} says {width}x{height} = "
            f"{width * height}; the message is inconsistent and is skipped"
        )
        raise ConvertError(text)
    translation = np.array(xyz(info.origin.position), dtype=np.float64)
    if not np.isfinite(translation).all():
        text = f"{ctx.topic}: {field}.origin.position is not finite ({translation.tolist()})"
        raise ConvertError(text)
    cells = data.reshape(height, width)
    cells.flags.writeable = False
    return Grid(
        topic=ctx.topic,
        entity_path=ctx.entity_path,
        frame=ctx.frame(msg.header.frame_id),
        cells=cells,
        resolution=resolution,
        translation=translation,
        quaternion=_unit_quaternion(info.origin.orientation, ctx.topic),
        options=options,
    )


def grid_from_msg(msg: Any, ctx: ConvertContext) -> Grid:
    """Validated view of an OccupancyGrid (no copy of the cells)."""
    size = (int(msg.info.width), int(msg.info.height))
    cells = np.asarray(msg.data, dtype=np.int8)
    return _grid(msg, msg.info, size, cells, ctx, options=ctx.options(GridOptions))


def _scheme(options: GridDrawingOptions, topic: str) -> str:
    if options.color_scheme is None:
        return "costmap" if "costmap" in topic else "map"
    return options.color_scheme


def color_scheme(grid: Grid) -> str:
    return _scheme(grid.options, grid.topic)


def cost_cells(costs: Any, options: GridDrawingOptions, topic: str) -> npt.NDArray[np.int8]:
    """A nav2 costmap's 0..255 costs as grid cells: translated for the palettes, as they are
    for ``raw`` (the byte values are the costs)."""
    data = np.asarray(costs, dtype=np.uint8)
    if _scheme(options, topic) == "raw":
        return data.view(np.int8)
    return COST_TO_OCCUPANCY[data]


def costmap_from_msg(msg: Any, ctx: ConvertContext) -> Grid:
    """Validated Grid of a nav2_msgs/Costmap."""
    meta = msg.metadata
    options = ctx.options(GridDrawingOptions)
    cells = cost_cells(msg.data, options, ctx.topic)
    return _grid(msg, meta, (int(meta.size_x), int(meta.size_y)), cells, ctx, options=options)


def grid_map(grid: Grid) -> rr.GridMap:
    scheme = color_scheme(grid)
    if scheme not in _COLORMAPS:
        text = (
            f"{grid.topic}: option color_scheme is {scheme!r}; choose one of "
            f"{', '.join(_COLORMAPS)}"
        )
        raise ConvertError(text)
    costmap = "costmap" in grid.topic
    opacity, draw_order = grid.options.opacity, grid.options.draw_order
    if opacity is None:
        opacity = 0.7 if costmap else 1.0
    if draw_order is None:
        # Costmaps over the map, the local one over the global one.
        draw_order = (1.0 + ("local" in grid.topic)) if costmap else 0.0
    height, width = grid.cells.shape
    return rr.GridMap(
        # tobytes of the flipped view is the one copy; Rerun takes bytes ~5x faster than arrays.
        data=np.flipud(grid.cells).tobytes(),
        format=rr.components.ImageFormat(
            width=width, height=height, color_model="L", channel_datatype="U8"
        ),
        cell_size=grid.resolution,
        translation=grid.translation,
        quaternion=rr.Quaternion(xyzw=grid.quaternion),
        opacity=opacity,
        draw_order=draw_order,
        colormap=_COLORMAPS[scheme],
    )


def grid_items(grid: Grid) -> list[LogEntry]:
    # A 0x0 grid (a costmap before its first update cycle) has nothing to draw.
    if grid.cells.size == 0:
        return []
    return [LogItem(grid.entity_path, (*frame_components(grid.frame), grid_map(grid)))]


def _store(ctx: ConvertContext, grid: Grid) -> None:
    ctx.robot_state.grids[grid.topic] = grid


def convert_grid(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    grid = grid_from_msg(msg, ctx)
    _store(ctx, grid)
    return grid_items(grid)


def grid_for_update(ctx: ConvertContext, target: str | None, grid_type: str = "OccupancyGrid") -> Grid:
    """The stored grid an update on ``ctx.topic`` patches: ``target`` (the update topic's option
    ``grid_topic``), else ``T`` for ``T_updates``."""
    if target is None:
        if not ctx.topic.endswith(UPDATES_SUFFIX):
            text = (
                f"{ctx.topic}: cannot tell which grid this {grid_type} update patches; name the "
                f"topic <grid topic>{UPDATES_SUFFIX} or set its option grid_topic"
            )
            raise ConvertError(text)
        target = ctx.topic[: -len(UPDATES_SUFFIX)]
    grid = ctx.robot_state.grids.get(target)
    if grid is None:
        text = (
            f"{ctx.topic}: no {grid_type} received yet on {target}; updates patch the last "
            "full grid, so they are dropped until one arrives"
        )
        raise ConvertError(text)
    return grid


def patched(
    grid: Grid, rectangle: tuple[int, int, int, int], patch: npt.NDArray[np.int8], topic: str
) -> Grid:
    """A new Grid with the update's rectangle (x, y, width, height) of cells ``patch`` written
    in (copy-on-write, see module doc)."""
    x, y, width, height = rectangle
    rows, cols = grid.cells.shape
    if x < 0 or y < 0 or x + width > cols or y + height > rows:
        text = (
            f"{topic}: update rectangle x={x} y={y} {width}x{height} does not fit the "
            f"{cols}x{rows} grid of {grid.topic}; the grid changed size, wait for the next full grid"
        )
        raise ConvertError(text)
    if patch.size != width * height:
        text = f"{topic}: update has {patch.size} cells for a {width}x{height} rectangle"
        raise ConvertError(text)
    cells = grid.cells.copy()
    cells[y : y + height, x : x + width] = patch.reshape(height, width)
    cells.flags.writeable = False
    return replace(grid, cells=cells)


def convert_update(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    rectangle = (int(msg.x), int(msg.y), int(msg.width), int(msg.height))
    grid = grid_for_update(ctx, ctx.options(GridUpdateOptions).grid_topic)
    grid = patched(grid, rectangle, np.asarray(msg.data, dtype=np.int8), ctx.topic)
    _store(ctx, grid)
    return grid_items(grid)


def convert_costmap(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    grid = costmap_from_msg(msg, ctx)
    _store(ctx, grid)
    return grid_items(grid)


def convert_costmap_update(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    """nav2_msgs/CostmapUpdate: costs of a rectangle of the costmap (``T_updates`` patches ``T``)."""
    grid = grid_for_update(ctx, ctx.options(CostmapUpdateOptions).grid_topic, "Costmap")
    cells = cost_cells(msg.data, grid.options, grid.topic)
    rectangle = (int(msg.x), int(msg.y), int(msg.size_x), int(msg.size_y))
    grid = patched(grid, rectangle, cells, ctx.topic)
    _store(ctx, grid)
    return grid_items(grid)


GRID = per_message(convert_grid)
GRID_UPDATE = per_message(convert_update)
# Costmaps are drawn, not turned into walls (walls.GRID_WALLS and UPDATE_WALLS are for the maps).
COSTMAP = per_message(convert_costmap)
COSTMAP_UPDATE = per_message(convert_costmap_update)
