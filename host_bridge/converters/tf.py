"""tf2_msgs/TFMessage -> Rerun named-frame transforms.

Every ROS frame ``f`` of robot ``R`` becomes the Rerun frame ``R/f``, so robots never collide.
/tf goes to one entity (``/<robot>/tf``), one row per transform stamped with its own header
time, as Rerun's own MCAP importer does. /tf_static is logged static, one entity per child frame,
because a static entity keeps only its last value.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import stamps_ns, vectors
from host_bridge.core.columns import Block, Columns
from host_bridge.core.contract import (
    ColumnsItem,
    LogEntry,
    LogItem,
    Run,
    TopicContext,
    component_columns,
    repeated_texts,
)
from host_bridge.core.options import TfOptions
from host_bridge.core.state import static_transform_path


def _is_static(ctx: TopicContext) -> bool:
    static = ctx.options(TfOptions).static
    return ctx.topic.endswith("/tf_static") if static is None else static


def _remember_children(ctx: TopicContext, children: Iterable[str]) -> None:
    # The joint-state kinematics leave frames alone that TF already drives (see joints.py).
    ctx.robot_state.tf_children.update(child.strip("/") for child in children)


def _transforms(block: Block) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """A block's translations (m, k, 3) and xyzw quaternions (m, k, 4), per block since the
    number of transforms k may differ between blocks; the all-zero (invalid) quaternion
    becomes the identity, as :func:`~host_bridge.converters._common.xyzw` does."""
    translations = vectors(block.numbers, "transforms.transform.translation")
    quaternions = vectors(block.numbers, "transforms.transform.rotation", "xyzw")
    quaternions[~quaternions.any(axis=-1), 3] = 1.0
    return translations, quaternions


def _static_items(columns: Columns, run: Run) -> list[LogEntry]:
    """One static entity per child frame; a later message's relation replaces an earlier one,
    so the items keep the run's order (/tf_static sends few messages: a loop is fine)."""
    run.robot_state.static_tf_root = run.entity_path
    ordered: list[tuple[int, int, LogItem]] = []
    for block in columns.blocks:
        translations, quaternions = _transforms(block)
        children = cast(tuple[str, ...], block.strings["transforms.child_frame_id"])
        parents = cast(tuple[str, ...], block.strings["transforms.header.frame_id"])
        _remember_children(run, children)
        for j, (child_id, parent_id) in enumerate(zip(children, parents, strict=True)):
            child, parent = run.frame(child_id), run.frame(parent_id)
            if child is None or parent is None:
                continue
            path = static_transform_path(run.robot, run.robot_state, child_id)
            for local, row in enumerate(block.rows.tolist()):
                transform = rr.Transform3D(
                    translation=translations[local, j],
                    quaternion=rr.Quaternion(xyzw=quaternions[local, j]),
                    parent_frame=parent,
                    child_frame=child,
                )
                ordered.append((row, j, LogItem(path, (transform,), static=True)))
    return [item for _, _, item in sorted(ordered, key=lambda entry: entry[:2])]


def convert_tf(run: Run) -> list[LogEntry]:
    """/tf: one row per transform on the topic entity, at its own header stamp; a block of
    messages with the same frames at a time (TF of k transforms each is k columns wide), read
    as columns."""
    columns = run.columns()
    if _is_static(run):
        return _static_items(columns, run)
    items: list[LogEntry] = []
    for block in columns.blocks:
        translations, quaternions = _transforms(block)
        stamps = stamps_ns(block.numbers, "transforms.header.stamp")
        children = cast(tuple[str, ...], block.strings["transforms.child_frame_id"])
        parents = cast(tuple[str, ...], block.strings["transforms.header.frame_id"])
        kept = [
            j for j, (child, parent) in enumerate(zip(children, parents, strict=True))
            if child.strip("/") and parent.strip("/")
        ]
        if not kept or not len(block.rows):
            continue
        _remember_children(run, (children[j] for j in kept))
        # Rows message by message, transform by transform, as the messages list them.
        width = len(kept)
        rows = np.repeat(block.rows, width)
        parent_frames = [cast(str, run.frame(parents[j])) for j in kept]
        child_frames = [cast(str, run.frame(children[j])) for j in kept]
        translations, quaternions = (
            values[:, kept].reshape(len(rows), -1) for values in (translations, quaternions)
        )
        for entries, times in run.times(stamps[:, kept].reshape(-1), rows):
            # Every row (no zero stamp, the usual case): the frames in order, once a message.
            every = len(entries) == len(rows)
            slots: npt.NDArray[np.intp] | int = len(block.rows) if every else entries % width
            columns_of_rows = component_columns(
                rr.Transform3D,
                translation=translations if every else translations[entries],
                quaternion=quaternions if every else quaternions[entries],
                parent_frame=repeated_texts(parent_frames, slots),
                child_frame=repeated_texts(child_frames, slots),
            )
            items.append(ColumnsItem(run.entity_path, columns_of_rows, times))
    return items


SPEC = convert_tf
