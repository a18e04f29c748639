"""sensor_msgs/LaserScan -> points (and optionally rays) in the scan's frame, vectorised.

Only finite returns with ``range_min <= r < range_max`` are drawn, laser_geometry's rule (which
RViz and most ROS consumers share): many drivers (Stage, several 2D lidars) report "no echo" as
exactly ``range_max``, which would otherwise draw an arc of points at the maximum range.
Options: ``mode`` points|rays|both, ``color_by`` range|intensity, ``colormap``, ``radius`` (m).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.colormap import apply_colormap
from host_bridge.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.converters._common import frame_components, header_frame
from host_bridge.errors import ConvertError
from host_bridge.options import LaserScanOptions

_MODES = ("points", "rays", "both")


def scan_points(msg: Any) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """Cartesian points of the valid returns, and the validity mask over all rays."""
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    angles = np.float64(msg.angle_min) + np.arange(ranges.size) * np.float64(msg.angle_increment)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & (ranges >= msg.range_min) & (ranges < msg.range_max)
    r = ranges[valid]
    a = angles[valid]
    points = np.empty((r.size, 3), dtype=np.float32)
    points[:, 0] = r * np.cos(a)
    points[:, 1] = r * np.sin(a)
    points[:, 2] = 0.0
    return points, valid


def convert_scan(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    options = ctx.options(LaserScanOptions)
    mode = options.mode
    if mode not in _MODES:
        msg_ = f"{ctx.topic}: laser option mode={mode!r} is not one of {', '.join(_MODES)}"
        raise ConvertError(msg_)
    points, valid = scan_points(msg)
    intensities = np.asarray(msg.intensities, dtype=np.float32)
    by_intensity = options.color_by == "intensity"
    if by_intensity and intensities.size == valid.size:
        colors = apply_colormap(intensities[valid], name=options.colormap)
    else:
        distance = np.hypot(points[:, 0], points[:, 1])
        colors = apply_colormap(
            distance, float(msg.range_min), float(msg.range_max),
            name=options.colormap,
        )
    frame = frame_components(header_frame(msg, ctx))
    items: list[LogEntry] = []
    if mode in ("points", "both"):
        points3d = rr.Points3D(points, colors=colors, radii=options.radius)
        items.append(LogItem(ctx.entity_path, (points3d, *frame)))
    if mode in ("rays", "both"):
        strips = np.stack([np.zeros_like(points), points], axis=1)
        items.append(
            LogItem(
                ctx.child_path("rays"),
                (rr.LineStrips3D(strips, colors=colors, radii=0.002), *frame),
            )
        )
    return items


SPEC = per_message(convert_scan)
