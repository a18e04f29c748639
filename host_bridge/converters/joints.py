"""JointState and JointTrajectory -> the link transforms of the robot model.

The kinematic table (:class:`RobotModel`) is put into ``ctx.robot_state.model`` by the URDF
converter (:mod:`host_bridge.converters.urdf`, whose ``kinematics.py`` holds the joint motion
used here); without it joint values mean nothing and messages are dropped with a ConvertError.
Each movable joint (revolute, continuous, prismatic) becomes one ``Transform3D(parent_frame=
<robot>/<parent link>, child_frame=<robot>/<child link>)`` at ``/<robot>/robot_model/joints/
<joint>``: joint origin times joint motion, the same relation robot_state_publisher would put on
/tf. Mimic joints follow their driver (``multiplier * driver + offset``) whenever the driver is in
the message, as robot_state_publisher does, even if the mimic joint is published too.

Until a joint state arrives the model stands at
:func:`~host_bridge.converters.urdf.kinematics.zero_positions`, logged by the URDF
converter as static rows on the /tf_static entity of each child link. Rerun resolves a frame
relation from one static entity and one temporal entity together (the static row holds until
the first temporal one, as /tf_static and /tf do), so the temporal rows logged here move the
link from their first stamp on, on every timeline.

/tf wins: Rerun refuses one frame relation logged on two temporal entities, so a joint whose
child link already arrived as a TF child frame (``ctx.robot_state.tf_children``, filled by the
TF converter, holding ROS ids or prefixed frame names) is left to /tf.

JointTrajectory drives the model with its first point: a trajectory starts at the robot's
current configuration, so that point is where the robot is when the command is issued; later
points are plans, not states, and would fight with /joint_states on the same entities.

Joint names the model lacks are ignored; they are reported once per topic through a
:class:`PartialConvertError` that still carries the transforms of the known joints.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import stamps_ns
from host_bridge.converters.urdf.kinematics import (
    MOVABLE_TYPES,
    FloatArray,
    follow_drivers,
    joint_motion,
)
from host_bridge.core.contract import (
    ColumnsItem,
    ConvertContext,
    LogEntry,
    LogItem,
    Run,
    TopicContext,
    per_message,
)
from host_bridge.core.state import JointModel, RobotModel
from host_bridge.errors import ConvertError, PartialConvertError


def joint_entity_path(robot: str, joint: str) -> str:
    return f"/{robot}/robot_model/joints/{rr.escape_entity_path_part(joint)}"


def link_frame(ctx: TopicContext, link: str) -> str:
    frame = ctx.frame(link)
    if frame is None:
        msg = f"{ctx.topic}: the robot model has a link with an empty name; name every link"
        raise ConvertError(msg)
    return frame


def tf_carries(ctx: TopicContext, link: str) -> bool:
    children = ctx.robot_state.tf_children
    return link in children or ctx.frame(link) in children


def joint_transform(ctx: TopicContext, joint: JointModel, value: float) -> rr.Transform3D:
    translations, quaternions = joint_motion(joint, np.array([value]))
    return rr.Transform3D(
        translation=translations[0],
        quaternion=rr.Quaternion(xyzw=quaternions[0]),
        parent_frame=link_frame(ctx, joint.parent),
        child_frame=link_frame(ctx, joint.child),
    )


def _require_model(ctx: TopicContext) -> RobotModel:
    model = ctx.robot_state.model
    if model is None:
        msg = (
            f"{ctx.topic}: robot {ctx.robot!r} has no robot model yet, so joint values cannot "
            "move its links; publish /robot_description (latched) or pass --urdf PATH"
        )
        raise ConvertError(msg)
    return model


def _joint_values(
    model: RobotModel, names: Sequence[str], positions: Any, ctx: ConvertContext, field: str
) -> tuple[dict[str, float], list[str]]:
    """Values of the joints this converter publishes, and the names the model lacks."""
    values_in = np.asarray(positions, dtype=np.float64)
    if len(values_in) == 0:
        return {}, []
    if len(values_in) != len(names):
        msg = (
            f"{ctx.topic}: {field} has {len(values_in)} values for {len(names)} joint names; "
            "the publisher must give one position per name"
        )
        raise ConvertError(msg)
    values = {
        name: float(value)
        for name, value in zip(names, values_in, strict=True)
        if name in model.joints and np.isfinite(value)
    }
    unknown = [name for name in names if name not in model.joints]
    follow_drivers(model, values)
    published = {
        name: value
        for name, value in values.items()
        if model.joints[name].type in MOVABLE_TYPES and not tf_carries(ctx, model.joints[name].child)
    }
    return published, unknown


@dataclass(slots=True)
class _ReportedJoints:
    """Per topic: the joint names the model lacks that were already reported."""

    names: set[str] = field(default_factory=set)


def _report_unknown(
    ctx: TopicContext, model: RobotModel, unknown: Iterable[str], items: list[LogEntry]
) -> list[LogEntry]:
    reported = ctx.state(_ReportedJoints).names
    new = sorted(set(unknown) - reported)
    if not new:
        return items
    reported.update(new)
    msg = (
        f"{ctx.topic}: joints {new} are not in the URDF {model.name!r} of robot {ctx.robot!r} "
        f"and are ignored (it has {sorted(model.joints)}); check that /robot_description "
        "describes the robot publishing these joints"
    )
    raise PartialConvertError(msg, items)


def _transform_items(ctx: ConvertContext, model: RobotModel, values: Mapping[str, float]) -> list[LogEntry]:
    return [
        LogItem(
            joint_entity_path(ctx.robot, name),
            (joint_transform(ctx, model.joints[name], value),),
        )
        for name, value in values.items()
    ]


def _block_values(
    model: RobotModel, names: Sequence[str], positions: FloatArray, ctx: TopicContext
) -> tuple[dict[str, FloatArray], list[str]]:
    """Per joint of the model a column of a block's positions, NaN where a message gives none
    (or a non-finite one), mimic joints following their drivers row by row; and the names the
    model lacks. The columnar counterpart of :func:`_joint_values`, with the same rules."""
    if positions.shape[1] == 0:
        return {}, []
    if positions.shape[1] != len(names):
        msg = (
            f"{ctx.topic}: position has {positions.shape[1]} values for {len(names)} joint "
            "names; the publisher must give one position per name"
        )
        raise ConvertError(msg)
    columns = {
        name: np.where(np.isfinite(positions[:, i]), positions[:, i], np.nan)
        for i, name in enumerate(names)
        if name in model.joints
    }
    for name in model.mimic_order:
        mimic = model.joints[name].mimic
        if mimic is None or mimic.joint not in columns:
            continue
        driver = columns[mimic.joint]
        own = columns.get(name, np.full(len(driver), np.nan))
        columns[name] = np.where(np.isnan(driver), own, mimic.multiplier * driver + mimic.offset)
    unknown = [name for name in names if name not in model.joints]
    return columns, unknown


def convert_joint_state(run: Run) -> list[LogEntry]:
    """One Transform3D column per joint over the run (read as columns); a row per message that
    moves the joint. Without a robot model this costs one check per run, not one per message."""
    model = _require_model(run)
    columns = run.columns()
    stamps = stamps_ns(columns)
    moved: dict[str, list[tuple[npt.NDArray[np.intp], FloatArray]]] = {}
    unknown: set[str] = set()
    for block in columns.blocks:
        names = cast(tuple[str, ...], block.strings["name"])
        values, missing = _block_values(model, names, block.numbers["position"], run)
        unknown.update(missing)
        for name, column in values.items():
            joint = model.joints[name]
            if joint.type not in MOVABLE_TYPES or tf_carries(run, joint.child):
                continue
            given = ~np.isnan(column)
            if given.any():
                moved.setdefault(name, []).append((block.rows[given], column[given]))
    items: list[LogEntry] = []
    for name, parts in moved.items():
        rows = np.concatenate([part_rows for part_rows, _ in parts])
        joint_values = np.concatenate([part_values for _, part_values in parts])
        order = np.argsort(rows, kind="stable")
        rows, joint_values = rows[order], joint_values[order]
        joint = model.joints[name]
        parent, child = link_frame(run, joint.parent), link_frame(run, joint.child)
        for entries, times in run.times(stamps[rows], rows):
            translations, quaternions = joint_motion(joint, joint_values[entries])
            transforms = rr.Transform3D.columns(
                translation=translations,
                quaternion=quaternions,
                parent_frame=[parent] * len(entries),
                child_frame=[child] * len(entries),
            )
            items.append(ColumnsItem(joint_entity_path(run.robot, name), list(transforms), times))
    return _report_unknown(run, model, unknown, items)


def convert_joint_trajectory(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    model = _require_model(ctx)
    if len(msg.points) == 0:
        return []
    values, unknown = _joint_values(
        model, msg.joint_names, msg.points[0].positions, ctx, "points[0].positions"
    )
    return _report_unknown(ctx, model, unknown, _transform_items(ctx, model, values))


# JointState's row combines this (the robot model moves) with scalars.JOINT_STATE (plots).
JOINT_STATE = convert_joint_state
JOINT_TRAJECTORY = per_message(convert_joint_trajectory)
