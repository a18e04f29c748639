"""nav_msgs/Odometry -> pose as a transform, a trail, and the twist as scalars.

The pose is logged as the entity's own (implicit) frame under the header frame, never as the
``child_frame_id`` relation: /tf usually carries odom -> base_link too, and Rerun refuses one
frame relation on two entities. Options: ``trail_length`` (points, default 1000),
``trail_min_distance`` (m, default 0.02).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters._common import frame_components, time_columns, xyz, xyzw
from host_bridge.registry import ColumnsItem, ConvertContext, ConverterSpec, LogEntry, LogItem

TWIST_SERIES = ("linear/x", "linear/y", "linear/z", "angular/x", "angular/y", "angular/z")


def _trail_items(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    trail: deque[list[float]] = ctx.state.setdefault(
        "trail", deque(maxlen=int(ctx.options.get("trail_length", 1000)))
    )
    position = xyz(msg.pose.pose.position)
    min_distance = float(ctx.options.get("trail_min_distance", 0.02))
    if trail and np.linalg.norm(np.subtract(position, trail[-1])) < min_distance:
        return []
    trail.append(position)
    if len(trail) < 2:
        return []
    strip = rr.LineStrips3D([np.asarray(trail, dtype=np.float32)], radii=0.01)
    return [
        LogItem(ctx.child_path("trail"), (strip, *frame_components(ctx.frame(msg.header.frame_id))))
    ]


def convert_odometry_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
    ctx0 = ctxs[0]
    times = time_columns(ctxs)
    pose = rr.Transform3D.columns(
        translation=np.array([xyz(m.pose.pose.position) for m in msgs], dtype=np.float64),
        quaternion=np.array([xyzw(m.pose.pose.orientation) for m in msgs], dtype=np.float64),
        parent_frame=[ctx0.frame(m.header.frame_id) or "tf#/" for m in msgs],
    )
    items: list[LogEntry] = [ColumnsItem(ctx0.entity_path, pose, times)]
    if not ctx0.state.get("axes_logged"):
        ctx0.state["axes_logged"] = True
        items.append(LogItem(ctx0.entity_path, (rr.TransformAxes3D(0.3),), static=True))
    twist = np.array(
        [xyz(m.twist.twist.linear) + xyz(m.twist.twist.angular) for m in msgs], dtype=np.float64
    )
    items.extend(
        ColumnsItem(ctx0.child_path("twist", name), rr.Scalars.columns(scalars=twist[:, i]), times)
        for i, name in enumerate(TWIST_SERIES)
    )
    for msg, ctx in zip(msgs, ctxs, strict=False):
        items.extend(_trail_items(msg, ctx))
    return items


def convert_odometry(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return convert_odometry_run([msg], [ctx])


CONVERTERS = {"nav_msgs/msg/Odometry": ConverterSpec(convert_odometry, convert_odometry_run)}
