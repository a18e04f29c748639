"""nav_msgs/Odometry -> pose as a transform with a trail (shared with PoseStamped), and the
twist as scalars.

The pose is logged as the entity's own (implicit) frame under the header frame, never as the
``child_frame_id`` relation: /tf usually carries odom -> base_link too, and Rerun refuses one
frame relation on two entities. Options as for poses (``trail_length``, ``axis_length``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.contract import ColumnsItem, ConvertContext, ConverterSpec, LogEntry
from host_bridge.converters._common import time_columns, xyz
from host_bridge.converters.geometry import pose_run

TWIST_SERIES = ("linear/x", "linear/y", "linear/z", "angular/x", "angular/y", "angular/z")


def convert_odometry_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
    items = pose_run([m.pose.pose for m in msgs], [m.header for m in msgs], ctxs)
    times = time_columns(ctxs)
    twist = np.array(
        [xyz(m.twist.twist.linear) + xyz(m.twist.twist.angular) for m in msgs], dtype=np.float64
    )
    items.extend(
        ColumnsItem(ctxs[0].child_path("twist", name), rr.Scalars.columns(scalars=twist[:, i]), times)
        for i, name in enumerate(TWIST_SERIES)
    )
    return items


def convert_odometry(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return convert_odometry_run([msg], [ctx])


SPEC = ConverterSpec(convert_odometry_run, single=convert_odometry)
