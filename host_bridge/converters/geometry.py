"""geometry_msgs: poses (trail, covariance), pose arrays, twists, wrenches, points, polygons.

A stamped pose becomes a transform from the header frame to the topic entity's own implicit
frame (``tf#<entity path>``), never a ``child_frame``: a pose topic is not a TF relation, and
naming a child frame would collide with /tf publishing the same frame. Everything the pose
carries along (trail, covariance) is drawn in the *header* frame, so it stays put while the
pose moves.

Options (:class:`~host_bridge.core.options.PoseOptions` and its kin): ``trail_length`` (points,
0 = off; a point is added once the pose moved more than 1 cm), ``trail_period`` (s between two
trail rows by the messages' stamps; every point is kept, but each row carries the whole trail, up
to 500 points: with a row for every message of a 30 Hz odometry a demo robot's small topics took
261-281 us of CPU a message, against 245-275 with 0.1 s; benchmarks/RESULTS.md), ``axis_length``
(m), ``arrow_length`` (PoseArray, m), ``sigma`` (covariance ellipsoid scale in standard
deviations).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import rerun as rr

from host_bridge.converters._common import frame_components, stamps_ns, vectors
from host_bridge.converters.scalars import vector_plots
from host_bridge.core.columns import Columns
from host_bridge.core.contract import (
    ColumnsItem,
    ConvertContext,
    Converter,
    LogEntry,
    LogItem,
    Run,
    TopicContext,
    component_columns,
    per_message,
)
from host_bridge.core.options import PoseArrayOptions, PoseCovarianceOptions, PoseOptions

Float64Array = npt.NDArray[np.float64]
RowIndex = npt.NDArray[np.intp]

# Standing still must not grow the trail: a pose only counts as moved beyond sensor jitter.
_TRAIL_MIN_STEP_M = 0.01


# --- helpers nav.py shares ------------------------------------------------------------------


def points_array(vectors: Sequence[Any]) -> Float64Array:
    """(N, 3) from objects with x, y, z (Point, Point32, Vector3)."""
    return np.array([(v.x, v.y, v.z) for v in vectors], dtype=np.float64).reshape(-1, 3)


def pose_arrays(poses: Sequence[Any]) -> tuple[Float64Array, Float64Array]:
    """Positions (N, 3) and quaternions (N, 4) in Rerun's xyzw order from geometry_msgs/Pose."""
    flat = np.array(
        [
            (
                p.position.x, p.position.y, p.position.z,
                p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w,
            )
            for p in poses
        ],
        dtype=np.float64,
    ).reshape(-1, 7)
    quats = flat[:, 3:]
    # Same rule as _common.xyzw: the all-zero (invalid) quaternion is drawn as identity.
    quats[~quats.any(axis=1), 3] = 1.0
    return flat[:, :3], quats


def x_axes(quats_xyzw: Float64Array) -> Float64Array:
    """Unit x axis of each rotation; quaternions need not be unit length (nor zero: see pose_arrays)."""
    q = quats_xyzw / np.linalg.norm(quats_xyzw, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)], axis=1,
    )


def pose_arrows(positions: Float64Array, quats_xyzw: Float64Array, length: float) -> rr.Arrows3D:
    """One arrow per pose along its x axis, as RViz draws a PoseArray."""
    return rr.Arrows3D(origins=positions, vectors=x_axes(quats_xyzw) * length)


def fixed_frame(ctx: TopicContext, frame: str | None) -> str:
    """The frame a pose is expressed in, also when its frame_id is empty.

    With an empty frame_id the pose transform hangs under the implicit frame of the topic
    entity's parent path; children of the topic entity (trail, covariance) must name that frame
    explicitly or they would inherit the pose and ride along with it.
    """
    if frame:
        return frame
    parent = "/" + ctx.entity_path.strip("/")
    return "tf#" + (parent.rsplit("/", 1)[0] or "/")


# --- stamped poses ------------------------------------------------------------------------------


@dataclass(slots=True)
class _Trail:
    """Per pose topic: the points of its trail and the frame they are in."""

    points: Float64Array = field(default_factory=lambda: np.empty((0, 3)))
    frame: str | None = None
    shown_ns: int | None = None
    shown_frame: str | None = None
    """The stamp and frame of the last trail row logged."""


@dataclass(frozen=True, slots=True)
class _Grown:
    """The rows of a run that moved its topic's trail, and the trail after each:
    ``points[begins[i]:ends[i]]`` after row ``rows[i]``."""

    rows: RowIndex
    points: Float64Array
    begins: npt.NDArray[np.int64]
    ends: npt.NDArray[np.int64]

    def strips(self, picked: RowIndex) -> pa.Array:
        """The trails after the rows ``picked`` (indices into ``rows``) as LineStrip3D cells,
        the Arrow array Rerun's batch takes as it is: a list of 2600 trails of 500 points
        converted by ``rr.LineStrips3D.columns`` was 5% of ``swanky-host --bag`` of
        nav2_turtlebot.mcap (py-spy). Only the trails of the rows shown are gathered."""
        starts = self.begins[picked]
        lengths = self.ends[picked] - starts
        offsets = np.zeros(len(picked) + 1, np.int32)
        np.cumsum(lengths, out=offsets[1:])
        points = self.points[np.repeat(starts - offsets[:-1], lengths) + np.arange(offsets[-1])]
        datatype = rr.components.LineStrip3D.arrow_type()
        vertices = pa.FixedSizeListArray.from_arrays(
            points.astype(np.float32).ravel(), type=datatype.value_type)
        return pa.ListArray.from_arrays(pa.array(offsets), vertices, type=datatype)


def _advance_trail(
    ctx: TopicContext, limit: int, positions: Float64Array, frames: Sequence[str | None],
) -> _Grown:
    """The rows that moved the ``limit`` points long trail, each with the trail after it;
    keeps the trail in the topic's state.

    Sequential by nature (each step compares with the last kept point), but per message, not
    per point, in Python floats (numpy's per-call cost is most of a message's); the kept trail
    stays an array, only the run's new points are Python's (turning the 500 kept points into
    lists and back at every live message was most of a trail's cost). A frame change restarts
    the trail: old points are in another frame.
    """
    if limit <= 0:
        nothing = np.empty(0, np.int64)
        return _Grown(np.empty(0, np.intp), np.empty((0, 3)), nothing, nothing)
    kept = ctx.state(_Trail)
    old = kept.points
    trail_frame = kept.frame
    start = 0  # where the trail in trail_frame begins in old + new
    last: list[float] | None = old[-1].tolist() if len(old) else None
    new: list[list[float]] = []
    rows: list[int] = []
    begins: list[int] = []
    for row, (position, frame) in enumerate(zip(positions.tolist(), frames, strict=True)):
        if frame != trail_frame:
            start, last, trail_frame = len(old) + len(new), None, frame
        if not all(map(math.isfinite, position)) or (
            last is not None and math.dist(position, last) <= _TRAIL_MIN_STEP_M
        ):
            continue
        new.append(position)
        last = position
        rows.append(row)
        begins.append(max(start, len(old) + len(new) - limit))
    every = np.concatenate([old, np.array(new, np.float64)]) if new else old
    kept.points, kept.frame = every[max(start, len(every) - limit) :], trail_frame
    ends = np.arange(len(old), len(every), dtype=np.int64) + 1
    return _Grown(np.array(rows, np.intp), every, np.array(begins, np.int64), ends)


def _shown(
    kept: _Trail, stamps: npt.NDArray[np.int64], frames: Sequence[str | None], period_s: float,
) -> RowIndex:
    """Which of the rows that grew the trail log it (indices into them): one ``period_s`` or more
    after the last logged by its stamp, and always one without a stamp, one earlier than the last
    (a bag looped, a simulation reset) or one in another frame (the trail restarted)."""
    if period_s <= 0:
        return np.arange(len(stamps))
    period_ns = round(period_s * 1e9)
    shown: list[int] = []
    for index, (stamp, frame) in enumerate(zip(stamps.tolist(), frames, strict=True)):
        last = kept.shown_ns
        if stamp and last is not None and last <= stamp < last + period_ns and frame == kept.shown_frame:
            continue
        shown.append(index)
        kept.shown_ns, kept.shown_frame = stamp or last, frame
    return np.array(shown, np.intp)


def _frame_rows(ctx: TopicContext, columns: Columns) -> list[tuple[str | None, RowIndex]]:
    """Rows of a run per header frame: a column cannot mix rows with and without a parent."""
    return [(ctx.frame(str(frame_id)), rows) for frame_id, rows in columns.groups("header.frame_id")]


def pose_columns_arrays(columns: Columns, path: str) -> tuple[Float64Array, Float64Array]:
    """Positions (n, 3) and xyzw quaternions (n, 4) of a run's geometry_msgs/Pose at ``path``,
    the all-zero (invalid) quaternion as identity, as :func:`pose_arrays`."""
    positions = vectors(columns, f"{path}.position")
    quats = vectors(columns, f"{path}.orientation", "xyzw")
    quats[~quats.any(axis=1), 3] = 1.0
    return positions, quats


def pose_columns(run: Run, path: str, options: PoseOptions | None = None) -> list[LogEntry]:
    """The pose at ``path`` of each message of a run, read as columns: transforms with axes,
    and the trail rows the run grew; ``options`` are the topic's (a covariance topic's record
    holds more)."""
    columns = run.columns()
    options = run.options(PoseOptions) if options is None else options
    positions, quats = pose_columns_arrays(columns, path)
    stamps = stamps_ns(columns)
    frame_rows = _frame_rows(run, columns)
    entries: list[LogEntry] = []
    for frame, rows in frame_rows:
        for picked, times in run.times(stamps[rows], rows):
            chosen = rows[picked]
            pose = [
                *rr.Transform3D.columns(
                    translation=positions[chosen],
                    quaternion=quats[chosen],
                    parent_frame=[frame] * len(chosen) if frame else None,
                ),
                *rr.TransformAxes3D.columns(axis_length=np.full(len(chosen), options.axis_length)),
            ]
            entries.append(ColumnsItem(run.entity_path, pose, times))
    frames: list[str | None] = [None] * len(run)
    for frame, rows in frame_rows:
        for row in rows.tolist():
            frames[row] = frame
    grown = _advance_trail(run, options.trail_length, positions, frames)
    shown = _shown(run.state(_Trail), stamps[grown.rows], [frames[row] for row in grown.rows.tolist()],
                   options.trail_period)
    if len(shown):
        rows = grown.rows[shown]
        for picked, times in run.times(stamps[rows], rows):
            trail = [
                *component_columns(rr.LineStrips3D, strips=grown.strips(shown[picked])),
                *rr.CoordinateFrame.columns(
                    frame=[fixed_frame(run, frames[row]) for row in rows[picked].tolist()]
                ),
            ]
            entries.append(ColumnsItem(run.child_path("trail"), trail, times))
    return entries


def _pose_stamped(run: Run) -> list[LogEntry]:
    return pose_columns(run, "pose")


def _quats_from_matrices(m: Float64Array) -> Float64Array:
    """xyzw quaternions of proper rotation matrices (N, 3, 3).

    Each row uses the branch with the largest diagonal term (Shepperd's method), which keeps
    the division well conditioned for every rotation, 180-degree turns included.
    """
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    m01, m02, m10 = m[:, 0, 1], m[:, 0, 2], m[:, 1, 0]
    m12, m20, m21 = m[:, 1, 2], m[:, 2, 0], m[:, 2, 1]
    x2 = 1.0 + m00 - m11 - m22
    y2 = 1.0 - m00 + m11 - m22
    z2 = 1.0 - m00 - m11 + m22
    w2 = 1.0 + m00 + m11 + m22
    # branches[b] is 4*q*(q's b-th component) in xyzw order.
    branches = np.stack(
        [
            np.stack([x2, m01 + m10, m02 + m20, m21 - m12], axis=1),
            np.stack([m01 + m10, y2, m12 + m21, m02 - m20], axis=1),
            np.stack([m02 + m20, m12 + m21, z2, m10 - m01], axis=1),
            np.stack([m21 - m12, m02 - m20, m10 - m01, w2], axis=1),
        ],
    )
    best = np.argmax(np.stack([x2, y2, z2, w2], axis=1), axis=1)
    q = branches[best, np.arange(len(m))]
    unit: Float64Array = q / np.linalg.norm(q, axis=1, keepdims=True)
    return unit


def covariance_ellipsoids(
    covariances: Float64Array, sigma: float,
) -> tuple[Float64Array, Float64Array]:
    """Half sizes (N, 3) and xyzw rotations (N, 4) of the ellipsoids of 3x3 position covariances
    (N, 3, 3): half sizes are sigma * sqrt(eigenvalue).

    Axes are sorted largest first so an axis-aligned covariance gets the identity rotation.
    """
    sym = 0.5 * (covariances + np.swapaxes(covariances, 1, 2))
    values, vectors_ = np.linalg.eigh(sym)
    values, vectors_ = values[:, ::-1], vectors_[:, :, ::-1]
    # eigh may return a reflection; flipping one eigenvector keeps the same ellipsoid.
    vectors_[:, :, 2] *= np.sign(np.linalg.det(vectors_))[:, None]
    half_sizes = sigma * np.sqrt(np.clip(values, 0.0, None))
    return half_sizes, _quats_from_matrices(vectors_)


def _pose_with_covariance(run: Run) -> list[LogEntry]:
    options = run.options(PoseCovarianceOptions)
    entries = pose_columns(run, "pose.pose", options)
    columns = run.columns()
    covariance = columns["pose.covariance"].astype(np.float64).reshape(-1, 6, 6)[:, :3, :3]
    # A non-finite covariance says nothing about the spread; the pose itself is still valid.
    finite = np.all(np.isfinite(covariance.reshape(len(covariance), -1)), axis=1)
    positions, _ = pose_columns_arrays(columns, "pose.pose")
    stamps = stamps_ns(columns)
    for frame, frame_rows in _frame_rows(run, columns):
        rows = frame_rows[finite[frame_rows]]
        if not len(rows):
            continue
        half_sizes, rotations = covariance_ellipsoids(covariance[rows], options.sigma)
        for picked, times in run.times(stamps[rows], rows):
            ellipsoids = [
                *rr.Ellipsoids3D.columns(
                    centers=positions[rows[picked]],
                    half_sizes=half_sizes[picked],
                    quaternions=rotations[picked],
                ),
                *rr.CoordinateFrame.columns(frame=[fixed_frame(run, frame)] * len(picked)),
            ]
            entries.append(ColumnsItem(run.child_path("covariance"), ellipsoids, times))
    return entries


def _pose_array(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    positions, quats = pose_arrays(msg.poses)
    arrows = pose_arrows(positions, quats, ctx.options(PoseArrayOptions).arrow_length)
    return [LogItem(ctx.entity_path, (arrows, *frame_components(ctx.frame(msg.header.frame_id))))]


# --- vectors: twist, wrench, vector3 ------------------------------------------------------------


def _vector_converter(fields: Mapping[str, str], colors: list[tuple[int, int, int]]) -> Converter:
    """Named Vector3 fields of a stamped message (``name: path``), each drawn as an arrow from
    the origin of the header frame and plotted (``<topic>/<name>``: x, y and z)."""
    names = list(fields)
    palette = np.array(colors, dtype=np.uint8)

    def convert(run: Run) -> list[LogEntry]:
        columns = run.columns()
        values = np.stack([vectors(columns, path) for path in fields.values()], axis=1)  # (n, k, 3)
        stamps = stamps_ns(columns)
        entries: list[LogEntry] = []
        for frame, frame_rows in _frame_rows(run, columns):
            for picked, times in run.times(stamps[frame_rows], frame_rows):
                rows = frame_rows[picked]
                flat = values[rows].reshape(-1, 3)
                arrows = rr.Arrows3D.columns(
                    vectors=flat,
                    origins=np.zeros_like(flat),
                    labels=names * len(rows),
                    colors=np.tile(palette, (len(rows), 1)),
                ).partition(np.full(len(rows), len(names)))
                frame_columns = rr.CoordinateFrame.columns(frame=[frame] * len(rows)) if frame else []
                entries.append(ColumnsItem(run.entity_path, [*arrows, *frame_columns], times))
        plots = [((name,), values[:, j]) for j, name in enumerate(names)]
        return [*entries, *vector_plots(run, plots, stamps)]

    return convert


_LINEAR_COLOR = (60, 140, 255)
_ANGULAR_COLOR = (255, 140, 30)


# --- points and polygons ------------------------------------------------------------------------


def _point_stamped(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    points = rr.Points3D(points_array([msg.point]))
    return [LogItem(ctx.entity_path, (points, *frame_components(ctx.frame(msg.header.frame_id))))]


def _polygon_stamped(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    vertices = points_array(msg.polygon.points)
    # Closed like RViz draws it; an empty polygon clears the previous one.
    strips = [np.concatenate([vertices, vertices[:1]])] if len(vertices) else []
    lines = rr.LineStrips3D(strips)
    return [LogItem(ctx.entity_path, (lines, *frame_components(ctx.frame(msg.header.frame_id))))]


POSE_STAMPED = _pose_stamped
POSE_WITH_COVARIANCE = _pose_with_covariance
POSE_ARRAY = per_message(_pose_array)
TWIST = _vector_converter(
    {"linear": "twist.linear", "angular": "twist.angular"}, [_LINEAR_COLOR, _ANGULAR_COLOR]
)
WRENCH = _vector_converter(
    {"force": "wrench.force", "torque": "wrench.torque"}, [_LINEAR_COLOR, _ANGULAR_COLOR]
)
VECTOR3 = _vector_converter({"vector": "vector"}, [_LINEAR_COLOR])
POINT = per_message(_point_stamped)
POLYGON = per_message(_polygon_stamped)
