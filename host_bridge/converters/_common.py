"""Small pieces several converters share: stamps, quaternions, frames."""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.core.columns import Columns
from host_bridge.core.contract import ConvertContext

# A block's number columns (columns.Block.numbers): read directly where a run's blocks differ in
# shape (TF messages of one and of two transforms).
Numbers = Mapping[str, npt.NDArray[Any]]


def stamp_ns(stamp: Any) -> int:
    """builtin_interfaces/Time (or a ROS 1 time) as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamps_ns(columns: Columns | Numbers, prefix: str = "header.stamp") -> npt.NDArray[np.int64]:
    """A Time field's columns (of a run, or of one of its blocks) as integer nanoseconds, shaped
    like its ``sec`` column."""
    seconds = columns[f"{prefix}.sec"].astype(np.int64)
    stamps: npt.NDArray[np.int64] = seconds * 1_000_000_000 + columns[f"{prefix}.nanosec"]
    return stamps


def vectors(columns: Columns | Numbers, path: str, axes: str = "xyz") -> npt.NDArray[np.float64]:
    """The ``axes`` of a Vector3/Point/Quaternion field (of a run, or of one of its blocks) as
    float64, shape (..., len(axes))."""
    return np.stack([columns[f"{path}.{axis}"] for axis in axes], axis=-1).astype(np.float64)


def header_frame(msg: Any, ctx: ConvertContext) -> str | None:
    return ctx.frame(msg.header.frame_id)


@lru_cache(maxsize=1024)
def frame_components(frame: str | None) -> tuple[rr.AsComponents, ...]:
    """``CoordinateFrame`` for a sensor entity, nothing when the message has no frame id. One
    archetype per frame, made once (logging does not change it): making it was a tenth of a live
    scan's conversion (Rerun's archetype constructor checks and converts its one string)."""
    return () if frame is None else (rr.CoordinateFrame(frame),)


def xyz(vector: Any) -> list[float]:
    return [float(vector.x), float(vector.y), float(vector.z)]


def xyzw(quaternion: Any) -> list[float]:
    """ROS quaternion in Rerun's xyzw order; the all-zero (invalid) one becomes identity."""
    q = [float(quaternion.x), float(quaternion.y), float(quaternion.z), float(quaternion.w)]
    return q if any(q) else [0.0, 0.0, 0.0, 1.0]
