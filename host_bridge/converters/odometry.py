"""nav_msgs/Odometry -> pose as a transform with a trail (shared with PoseStamped), and the
twist as two plots, ``twist/linear`` and ``twist/angular``, of an x, y and z series each.

The pose is logged as the entity's own (implicit) frame under the header frame, never as the
``child_frame_id`` relation: /tf usually carries odom -> base_link too, and Rerun refuses one
frame relation on two entities. Options as for poses (``trail_length``, ``axis_length``).
"""

from __future__ import annotations

from host_bridge.converters._common import stamps_ns, vectors
from host_bridge.converters.geometry import pose_columns
from host_bridge.converters.scalars import vector_plots
from host_bridge.core.contract import LogEntry, Run


def convert_odometry(run: Run) -> list[LogEntry]:
    """The pose and its trail, and the twist's plots, read as columns."""
    columns = run.columns()
    twist = [(("twist", name), vectors(columns, f"twist.twist.{name}")) for name in ("linear", "angular")]
    return [*pose_columns(run, "pose.pose"), *vector_plots(run, twist, stamps_ns(columns))]


SPEC = convert_odometry
