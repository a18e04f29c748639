"""geometry_msgs: poses (trail, covariance), pose arrays, twists, wrenches, points, polygons.

A stamped pose becomes a transform from the header frame to the topic entity's own implicit
frame (``tf#<entity path>``), never a ``child_frame``: a pose topic is not a TF relation, and
naming a child frame would collide with /tf publishing the same frame. Everything the pose
carries along (trail, covariance) is drawn in the *header* frame, so it stays put while the
pose moves.

Options (:class:`~host_bridge.options.PoseOptions` and its kin): ``trail_length`` (points,
0 = off; a point is added once the pose moved more than 1 cm), ``axis_length`` (m),
``arrow_length`` (PoseArray, m), ``sigma`` (covariance ellipsoid scale in standard deviations).
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.contract import ColumnsItem, ConvertContext, ConverterSpec, LogEntry, LogItem, per_message
from host_bridge.converters._common import frame_components, time_columns
from host_bridge.options import PoseArrayOptions, PoseCovarianceOptions, PoseOptions

Float64Array = npt.NDArray[np.float64]
RowIndex = npt.NDArray[np.intp]

# Standing still must not grow the trail: a pose only counts as moved beyond sensor jitter.
_TRAIL_MIN_STEP_M = 0.01
_COMPONENTS = ("x", "y", "z")


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


def fixed_frame(ctx: ConvertContext, frame: str | None) -> str:
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


def _advance_trail(
    ctx: ConvertContext, limit: int, positions: Float64Array, frames: Sequence[str | None],
) -> list[tuple[int, Float64Array]]:
    """(row, trail after that row) for every row that moved the ``limit`` points long trail;
    keeps it in the topic's state.

    Sequential by nature (each step compares with the last kept point), but per message, not
    per point. A frame change restarts the trail: old points are in another frame.
    """
    if limit <= 0:
        return []
    kept = ctx.state(_Trail)
    trail, trail_frame = kept.points, kept.frame
    grown: list[tuple[int, Float64Array]] = []
    for row, (position, frame) in enumerate(zip(positions, frames, strict=True)):
        if frame != trail_frame:
            trail, trail_frame = np.empty((0, 3)), frame
        if not np.isfinite(position).all() or (
            len(trail) and np.linalg.norm(position - trail[-1]) <= _TRAIL_MIN_STEP_M
        ):
            continue
        trail = np.concatenate([trail[max(0, len(trail) - limit + 1) :], position[None]])
        grown.append((row, trail))
    kept.points, kept.frame = trail, trail_frame
    return grown


def _group_rows(frames: Sequence[str | None]) -> list[tuple[str | None, RowIndex]]:
    """Rows of a run per frame: a column cannot mix rows with and without a parent frame."""
    index = {frame: i for i, frame in enumerate(dict.fromkeys(frames))}
    labels = np.array([index[frame] for frame in frames])
    return [(frame, np.flatnonzero(labels == i)) for frame, i in index.items()]


def pose_run(
    poses: Sequence[Any], headers: Sequence[Any], ctxs: Sequence[ConvertContext],
    options: PoseOptions | None = None,
) -> list[LogEntry]:
    """Pose transforms with axes, and the trail rows the run grew; ``options`` are the topic's
    (a covariance topic's record holds more than PoseOptions)."""
    ctx = ctxs[0]
    options = ctx.options(PoseOptions) if options is None else options
    frames = [ctx.frame(h.frame_id) for h in headers]
    positions, quats = pose_arrays(poses)
    axis_length = options.axis_length
    entries: list[LogEntry] = []
    for frame, rows in _group_rows(frames):
        columns = [
            *rr.Transform3D.columns(
                translation=positions[rows],
                quaternion=quats[rows],
                parent_frame=[frame] * len(rows) if frame else None,
            ),
            *rr.TransformAxes3D.columns(axis_length=np.full(len(rows), axis_length)),
        ]
        times = time_columns([ctxs[i] for i in rows])
        entries.append(ColumnsItem(ctx.entity_path, columns, times))
    grown = _advance_trail(ctx, options.trail_length, positions, frames)
    if grown:
        columns = [
            *rr.LineStrips3D.columns(strips=[trail for _, trail in grown]),
            *rr.CoordinateFrame.columns(frame=[fixed_frame(ctx, frames[row]) for row, _ in grown]),
        ]
        times = time_columns([ctxs[row] for row, _ in grown])
        entries.append(ColumnsItem(ctx.child_path("trail"), columns, times))
    return entries


def _pose_stamped(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return pose_run([msg.pose], [msg.header], [ctx])


def _pose_stamped_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
    if not msgs:
        return []
    return pose_run([m.pose for m in msgs], [m.header for m in msgs], ctxs)


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
    centers: Float64Array, covariances: Float64Array, sigma: float,
) -> rr.Ellipsoids3D:
    """Ellipsoids of 3x3 position covariances (N, 3, 3): half sizes are sigma * sqrt(eigenvalue).

    Axes are sorted largest first so an axis-aligned covariance gets the identity rotation.
    """
    sym = 0.5 * (covariances + np.swapaxes(covariances, 1, 2))
    values, vectors = np.linalg.eigh(sym)
    values, vectors = values[:, ::-1], vectors[:, :, ::-1]
    # eigh may return a reflection; flipping one eigenvector keeps the same ellipsoid.
    vectors[:, :, 2] *= np.sign(np.linalg.det(vectors))[:, None]
    half_sizes = sigma * np.sqrt(np.clip(values, 0.0, None))
    return rr.Ellipsoids3D(
        centers=centers, half_sizes=half_sizes, quaternions=_quats_from_matrices(vectors),
    )


def _pose_with_covariance(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    options = ctx.options(PoseCovarianceOptions)
    entries = pose_run([msg.pose.pose], [msg.header], [ctx], options)
    covariance = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    # A non-finite covariance says nothing about the spread; the pose itself is still valid.
    if np.isfinite(covariance).all():
        position, _ = pose_arrays([msg.pose.pose])
        ellipsoid = covariance_ellipsoids(
            position, covariance[None], options.sigma,
        )
        frame = rr.CoordinateFrame(fixed_frame(ctx, ctx.frame(msg.header.frame_id)))
        entries.append(LogItem(ctx.child_path("covariance"), (ellipsoid, frame)))
    return entries


def _pose_array(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    positions, quats = pose_arrays(msg.poses)
    arrows = pose_arrows(positions, quats, ctx.options(PoseArrayOptions).arrow_length)
    return [LogItem(ctx.entity_path, (arrows, *frame_components(ctx.frame(msg.header.frame_id))))]


# --- vectors: twist, wrench, vector3 ------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _VectorSet:
    """Named Vector3 fields of a stamped message, each drawn as an arrow and plotted per axis."""

    names: tuple[str, ...]
    getters: tuple[Callable[[Any], Any], ...]
    colors: npt.NDArray[np.uint8]

    def values(self, msgs: Sequence[Any]) -> Float64Array:
        """(N, len(names), 3)."""
        vectors = points_array([get(m) for m in msgs for get in self.getters])
        return vectors.reshape(len(msgs), -1, 3)

    def scalar_paths(self, ctx: ConvertContext) -> list[list[str]]:
        return [[ctx.child_path(name, axis) for axis in _COMPONENTS] for name in self.names]


def _vector_set(fields: dict[str, str], colors: list[tuple[int, int, int]]) -> _VectorSet:
    return _VectorSet(
        names=tuple(fields),
        getters=tuple(operator.attrgetter(path) for path in fields.values()),
        colors=np.array(colors, dtype=np.uint8),
    )


_LINEAR_COLOR = (60, 140, 255)
_ANGULAR_COLOR = (255, 140, 30)
_TWIST = _vector_set(
    {"linear": "twist.linear", "angular": "twist.angular"}, [_LINEAR_COLOR, _ANGULAR_COLOR],
)
_WRENCH = _vector_set(
    {"force": "wrench.force", "torque": "wrench.torque"}, [_LINEAR_COLOR, _ANGULAR_COLOR],
)
_VECTOR3 = _vector_set({"vector": "vector"}, [_LINEAR_COLOR])


def _vector_converter(spec: _VectorSet) -> ConverterSpec:
    def convert_run(msgs: Sequence[Any], ctxs: Sequence[ConvertContext]) -> list[LogEntry]:
        if not msgs:
            return []
        ctx = ctxs[0]
        values = spec.values(msgs)
        n, k = values.shape[:2]
        flat = values.reshape(-1, 3)
        arrows = rr.Arrows3D.columns(
            vectors=flat,
            origins=np.zeros_like(flat),
            labels=list(spec.names) * n,
            colors=np.tile(spec.colors, (n, 1)),
        ).partition(np.full(n, k))
        times = time_columns(ctxs)
        entries: list[LogEntry] = [ColumnsItem(ctx.entity_path, list(arrows), times)]
        frames = [ctx.frame(m.header.frame_id) for m in msgs]
        entries.extend(
            ColumnsItem(
                ctx.entity_path,
                list(rr.CoordinateFrame.columns(frame=[frame] * len(rows))),
                time_columns([ctxs[i] for i in rows]),
            )
            for frame, rows in _group_rows(frames)
            if frame
        )
        for j, paths in enumerate(spec.scalar_paths(ctx)):
            entries.extend(
                ColumnsItem(path, list(rr.Scalars.columns(scalars=values[:, j, axis])), times)
                for axis, path in enumerate(paths)
            )
        return entries

    def convert(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
        return convert_run([msg], [ctx])

    return ConverterSpec(convert_run, single=convert)


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


POSE_STAMPED = ConverterSpec(_pose_stamped_run, single=_pose_stamped)
POSE_WITH_COVARIANCE = per_message(_pose_with_covariance)
POSE_ARRAY = per_message(_pose_array)
TWIST = _vector_converter(_TWIST)
WRENCH = _vector_converter(_WRENCH)
VECTOR3 = _vector_converter(_VECTOR3)
POINT = per_message(_point_stamped)
POLYGON = per_message(_polygon_stamped)
