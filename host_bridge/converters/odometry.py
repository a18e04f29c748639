"""nav_msgs/Odometry -> pose as a transform with a trail (shared with PoseStamped), and the
twist as scalars.

The pose is logged as the entity's own (implicit) frame under the header frame, never as the
``child_frame_id`` relation: /tf usually carries odom -> base_link too, and Rerun refuses one
frame relation on two entities. Options as for poses (``trail_length``, ``axis_length``).
"""

from __future__ import annotations

import rerun as rr

from host_bridge.converters._common import stamps_ns, vectors
from host_bridge.converters.geometry import pose_columns
from host_bridge.core.contract import ColumnsItem, LogEntry, Run

TWIST_SERIES = ("linear/x", "linear/y", "linear/z", "angular/x", "angular/y", "angular/z")


def convert_odometry(run: Run) -> list[LogEntry]:
    """The pose and its trail, and the twist's plots, read as columns."""
    items = pose_columns(run, "pose.pose")
    columns = run.columns()
    twist = [
        *vectors(columns, "twist.twist.linear").T,
        *vectors(columns, "twist.twist.angular").T,
    ]
    for rows, times in run.times(stamps_ns(columns)):
        items.extend(
            ColumnsItem(run.child_path("twist", name), rr.Scalars.columns(scalars=values[rows]), times)
            for name, values in zip(TWIST_SERIES, twist, strict=True)
        )
    return items


SPEC = convert_odometry
