"""tf2_msgs/TFMessage -> Rerun named-frame transforms.

Every ROS frame ``f`` of robot ``R`` becomes the Rerun frame ``R/f``, so robots never collide.
/tf goes to one entity (``/<robot>/tf``), one row per transform stamped with its own header
time, as Rerun's own MCAP importer does. /tf_static is logged static, one entity per child frame,
because a static entity keeps only its last value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.contract import ColumnsItem, ConvertContext, ConverterSpec, LogEntry, LogItem
from host_bridge.converters._common import stamp_ns, time_columns, xyz, xyzw
from host_bridge.options import TfOptions
from host_bridge.state import RobotState


def _is_static(ctx: ConvertContext) -> bool:
    static = ctx.options(TfOptions).static
    return ctx.topic.endswith("/tf_static") if static is None else static


def _remember_children(ctx: ConvertContext, transforms: Sequence[Any]) -> None:
    # The joint-state kinematics leave frames alone that TF already drives (see joints.py).
    ctx.robot_state.tf_children.update(t.child_frame_id.strip("/") for t in transforms)


def static_transform_path(robot: str, robot_state: RobotState, child_frame_id: str) -> str:
    """The one static entity holding the relation into ``child_frame_id``.

    Rerun wants each frame relation on a single entity. A URDF's fixed joints are usually also
    on /tf_static (robot_state_publisher), so the model logs them here too and whichever of the
    two arrives last holds the value. The root is the robot's /tf_static entity (configurable),
    ``/<robot>/tf_static`` until a /tf_static message shows it.
    """
    root = robot_state.static_tf_root or f"/{robot}/tf_static"
    return f"{root}/{rr.escape_entity_path_part(child_frame_id.strip('/'))}"


def _static_items(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    _remember_children(ctx, msg.transforms)
    ctx.robot_state.static_tf_root = ctx.entity_path
    items: list[LogEntry] = []
    for t in msg.transforms:
        child = ctx.frame(t.child_frame_id)
        parent = ctx.frame(t.header.frame_id)
        if child is None or parent is None:
            continue
        path = static_transform_path(ctx.robot, ctx.robot_state, t.child_frame_id)
        transform = rr.Transform3D(
            translation=xyz(t.transform.translation),
            quaternion=rr.Quaternion(xyzw=xyzw(t.transform.rotation)),
            parent_frame=parent,
            child_frame=child,
        )
        items.append(LogItem(path, (transform,), static=True))
    return items


def convert_tf_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
    if _is_static(ctxs[0]):
        return [item for msg, ctx in zip(msgs, ctxs, strict=False) for item in _static_items(msg, ctx)]
    rows = [
        (t, ctx)
        for msg, ctx in zip(msgs, ctxs, strict=False)
        for t in msg.transforms
        if t.child_frame_id.strip("/") and t.header.frame_id.strip("/")
    ]
    if not rows:
        return []
    ctx0 = ctxs[0]
    _remember_children(ctx0, [t for t, _ in rows])
    columns = rr.Transform3D.columns(
        translation=np.array([xyz(t.transform.translation) for t, _ in rows], dtype=np.float64),
        quaternion=np.array([xyzw(t.transform.rotation) for t, _ in rows], dtype=np.float64),
        parent_frame=[ctx0.frame(t.header.frame_id) or "" for t, _ in rows],
        child_frame=[ctx0.frame(t.child_frame_id) or "" for t, _ in rows],
    )
    times = time_columns([c for _, c in rows], ros_ns=[stamp_ns(t.header.stamp) for t, _ in rows])
    return [ColumnsItem(ctx0.entity_path, columns, times)]


def convert_tf(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return convert_tf_run([msg], [ctx])


SPEC = ConverterSpec(convert_tf_run, single=convert_tf)
