"""nav_msgs: planned paths and grid cells (costmap obstacles, frontiers) in their header frame.

Path options (:class:`~host_bridge.core.options.PathOptions`): ``arrows`` (draw each pose's heading
too), ``arrow_length`` (m).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters._common import frame_components
from host_bridge.converters.geometry import points_array, pose_arrays, pose_arrows
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.core.options import PathOptions

# GridCells are flat squares in RViz; a box this thin reads as a tile without z-fighting the map.
_CELL_THICKNESS_M = 0.01


def _path(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    """One strip through all poses; the per-pose frame_ids are ignored, as RViz does."""
    positions, quats = pose_arrays([stamped.pose for stamped in msg.poses])
    frame = frame_components(ctx.frame(msg.header.frame_id))
    # An empty path clears the previous plan instead of leaving it on screen.
    strips = [positions] if len(positions) else []
    entries: list[LogEntry] = [LogItem(ctx.entity_path, (rr.LineStrips3D(strips), *frame))]
    options = ctx.options(PathOptions)
    if options.arrows:
        arrows = pose_arrows(positions, quats, options.arrow_length)
        entries.append(LogItem(ctx.child_path("poses"), (arrows, *frame)))
    return entries


def _grid_cells(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    half_size = 0.5 * np.array([msg.cell_width, msg.cell_height, _CELL_THICKNESS_M])
    boxes = rr.Boxes3D(
        centers=points_array(msg.cells),
        half_sizes=[half_size],
        fill_mode=rr.components.FillMode.Solid,
    )
    return [LogItem(ctx.entity_path, (boxes, *frame_components(ctx.frame(msg.header.frame_id))))]


PATH = per_message(_path)
GRID_CELLS = per_message(_grid_cells)
