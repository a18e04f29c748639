"""JointState and JointTrajectory -> the link transforms of the robot model.

The kinematic table (:class:`RobotModel`) is put into ``ctx.robot_state.model`` by the URDF
converter; without it joint values mean nothing and messages are dropped with a ConvertError.
Each movable joint (revolute, continuous, prismatic) becomes one ``Transform3D(parent_frame=
<robot>/<parent link>, child_frame=<robot>/<child link>)`` at ``/<robot>/robot_model/joints/
<joint>``: joint origin times joint motion, the same relation robot_state_publisher would put on
/tf. Mimic joints follow their driver (``multiplier * driver + offset``) whenever the driver is in
the message, as robot_state_publisher does, even if the mimic joint is published too.

Until a joint state arrives the model stands at :func:`zero_positions`, logged by the URDF
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

from host_bridge.contract import (
    ColumnsItem,
    ConvertContext,
    LogEntry,
    LogItem,
    Run,
    TopicContext,
    per_message,
)
from host_bridge.converters._common import stamps_ns
from host_bridge.errors import ConvertError, PartialConvertError
from host_bridge.state import JointModel, RobotModel

MOVABLE_TYPES = frozenset({"revolute", "continuous", "prismatic"})

FloatArray = npt.NDArray[np.float64]


def pose_of_matrix(matrix: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Translation and unit quaternion (x, y, z, w) of a 4x4 rigid transform."""
    r = matrix[:3, :3]
    # Shepperd: take the square root of the largest of 4w², 4x², 4y², 4z² for stability.
    diagonal = np.array([np.trace(r), r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(diagonal))
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + diagonal[0])
        q = [
            (r[2, 1] - r[1, 2]) / (4 * w),
            (r[0, 2] - r[2, 0]) / (4 * w),
            (r[1, 0] - r[0, 1]) / (4 * w),
            w,
        ]
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        v = 0.5 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[m, m])
        q = [0.0, 0.0, 0.0, (r[m, j] - r[j, m]) / (4 * v)]
        q[i] = v
        q[j] = (r[j, i] + r[i, j]) / (4 * v)
        q[m] = (r[m, i] + r[i, m]) / (4 * v)
    quaternion = np.asarray(q, dtype=np.float64)
    return np.asarray(matrix[:3, 3], dtype=np.float64), quaternion / np.linalg.norm(quaternion)


def robot_model(name: str, joints: Iterable[JointModel], root: str | None = None) -> RobotModel:
    table = {joint.name: joint for joint in joints}
    return RobotModel(name=name, joints=table, mimic_order=_mimic_order(table), root=root)


def _mimic_order(joints: Mapping[str, JointModel]) -> tuple[str, ...]:
    """Mimic joints with each driver before the joints that follow it (mimic chains). A loop
    is followed once round. Iterative: a chain of thousands of mimic joints listed followers
    first exceeded Python's recursion limit and lost the whole model."""
    order: list[str] = []
    placed: set[str] = set()
    for start in joints:
        chain: dict[str, None] = {}  # ordered: ``start`` and the mimic drivers it follows
        name = start
        while name in joints and name not in placed and name not in chain:
            mimic = joints[name].mimic
            if mimic is None:
                break
            chain[name] = None
            name = mimic.joint
        for follower in reversed(chain):
            placed.add(follower)
            order.append(follower)
    return tuple(order)


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


def joint_motion(joint: JointModel, values: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Translations (n, 3) and quaternions (n, 4, xyzw) of parent -> child at ``values``."""
    count = len(values)
    translations = np.tile(joint.translation, (count, 1))
    quaternions = np.tile(joint.quaternion, (count, 1))
    if joint.type == "prismatic":
        translations += values[:, None] * (joint.rotation @ joint.axis)
    elif joint.type in ("revolute", "continuous"):
        half = values / 2.0
        motion = np.column_stack([np.outer(np.sin(half), joint.axis), np.cos(half)])
        quaternions = _quaternion_product(quaternions, motion)
    return translations, quaternions


def _quaternion_product(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise Hamilton product of (n, 4) xyzw quaternions."""
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.column_stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def joint_transform(ctx: TopicContext, joint: JointModel, value: float) -> rr.Transform3D:
    translations, quaternions = joint_motion(joint, np.array([value]))
    return rr.Transform3D(
        translation=translations[0],
        quaternion=rr.Quaternion(xyzw=quaternions[0]),
        parent_frame=link_frame(ctx, joint.parent),
        child_frame=link_frame(ctx, joint.child),
    )


def _follow_drivers(model: RobotModel, values: dict[str, float]) -> None:
    """Set each mimic joint whose driver is in ``values`` to ``multiplier * driver + offset``."""
    for name in model.mimic_order:
        mimic = model.joints[name].mimic
        if mimic is not None and mimic.joint in values:
            values[name] = mimic.multiplier * values[mimic.joint] + mimic.offset


def zero_positions(model: RobotModel) -> dict[str, float]:
    """Every joint at 0 and mimic joints where a driver at 0 puts them (their offset): the pose
    RViz and Rerun's URDF loader show until the first joint state."""
    values = dict.fromkeys(model.joints, 0.0)
    _follow_drivers(model, values)
    return values


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
    _follow_drivers(model, values)
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
