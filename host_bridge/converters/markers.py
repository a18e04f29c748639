"""visualization_msgs Marker / MarkerArray -> Rerun primitives, one entity per marker.

Each marker lives at ``<topic>/<ns>/<id>`` (the ns escaped; the empty ns is ``_``) with a
``Transform3D`` from its header frame (``parent_frame``) to the entity's implicit frame, so the
geometry is logged in marker-local coordinates as RViz draws it. The marker scale goes into the
geometry (sizes, line widths, vertex positions), never into the transform, so line widths and
point radii stay in metres. An empty frame_id leaves the parent to the entity tree.

Lifetimes: a converter cannot schedule, so a marker with lifetime > 0 is logged together with a
``Clear`` of its entity whose times are the message's times plus the lifetime, on every timeline.
Markers are usually republished before they expire (10 Hz with a 1 s lifetime); the earlier
Clear would then blank the fresh marker until its next message, so while an earlier Clear is
still pending and the new marker outlives it, the marker is logged once more 1 ns after it.

frame_locked is ignored: Rerun resolves the header frame through the transform tree at view
time, which is what frame_locked=true asks for; an unlocked marker in a moving frame follows the
frame instead of staying where it was published.

A mesh marker's ``mesh_resource`` (``package://``, ``file://``, a path) is read through the
robot's resolver, the one that finds its model's meshes (``--package-path``, the ROS package
paths, the robot's relay), once per topic and URI.

A problem with one marker (unknown type, odd LINE_LIST, unreadable mesh) skips that marker
only, so its siblings in a MarkerArray still show. The message raises ConvertError when nothing
else was converted; otherwise each distinct problem is logged once per topic as a warning
``TextLog`` at the topic entity.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from operator import attrgetter
from typing import Any
from urllib.parse import urlparse

import numpy as np
import numpy.typing as npt
import rerun as rr

from host_bridge.converters._common import stamp_ns, xyz, xyzw
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message
from host_bridge.errors import ConvertError

(ARROW, CUBE, SPHERE, CYLINDER, LINE_STRIP, LINE_LIST, CUBE_LIST, SPHERE_LIST, POINTS,
 TEXT_VIEW_FACING, MESH_RESOURCE, TRIANGLE_LIST) = range(12)
ADD, DELETE, DELETEALL = 0, 2, 3

_XYZ = attrgetter("x", "y", "z")
_RGBA = attrgetter("r", "g", "b", "a")
_ORIGIN = np.zeros((1, 3))
_SOLID = rr.components.FillMode.Solid

Archetypes = tuple[rr.AsComponents, ...]


@dataclass(slots=True)
class MarkerTopic:
    """What one marker topic keeps between messages."""

    # Live marker entity -> its marker type (an ADD of another type clears the old geometry).
    types: dict[str, int] = field(default_factory=dict)
    # Marker entity -> the times of the lifetime Clear still pending for it.
    expiry: dict[str, dict[str, int]] = field(default_factory=dict)
    # Mesh URI -> (file bytes, media type): meshes come again with every marker.
    meshes: dict[str, tuple[bytes, Any]] = field(default_factory=dict)
    # Problems already logged for this topic.
    reported: set[str] = field(default_factory=set)


def _points(marker: Any) -> npt.NDArray[np.float64]:
    return np.array(list(map(_XYZ, marker.points)), dtype=np.float64).reshape(-1, 3)


def _rgba8(colors: Sequence[Any]) -> npt.NDArray[np.uint8]:
    """std_msgs/ColorRGBA floats (0..1) as (N, 4) RGBA bytes."""
    return _bytes(list(map(_RGBA, colors)))


def _bytes(rgba: Sequence[tuple[float, float, float, float]]) -> npt.NDArray[np.uint8]:
    """RGBA floats (0..1) as (N, 4) bytes."""
    values = np.array(rgba, dtype=np.float64).reshape(-1, 4)
    return np.clip(np.rint(values * 255.0), 0, 255).astype(np.uint8)


def _color(marker: Any) -> npt.NDArray[np.uint8]:
    return _rgba8([marker.color])


def _point_colors(marker: Any, count: int) -> npt.NDArray[np.uint8]:
    """One colour per point when the marker has them, else its single colour (which splats)."""
    return _rgba8(marker.colors) if count and len(marker.colors) == count else _color(marker)


def _scale(marker: Any) -> npt.NDArray[np.float64]:
    return np.array(_XYZ(marker.scale), dtype=np.float64)


def _arrow(marker: Any, ctx: ConvertContext) -> Archetypes:
    scale, points = _scale(marker), _points(marker)
    if len(points) == 0:
        # Pose form: length scale.x along +x, shaft diameter scale.y.
        origins, vectors, radius = _ORIGIN, np.array([[scale[0], 0.0, 0.0]]), scale[1] / 2
    elif len(points) == 2:
        # Two-point form: shaft diameter scale.x.
        origins, vectors, radius = points[:1], points[1:] - points[:1], scale[0] / 2
    else:
        msg = f"ARROW has {len(points)} points; it takes none (pose form) or exactly 2"
        raise ConvertError(msg)
    return (rr.Arrows3D(origins=origins, vectors=vectors, radii=[radius], colors=_color(marker)),)


@lru_cache(maxsize=256)
def _solid(marker_type: int, scale: tuple[float, float, float],
           rgba: tuple[float, float, float, float]) -> Archetypes:
    """The geometry of a CUBE, SPHERE or CYLINDER (the pose places it), made once per size and
    colour: such a topic usually moves a few shapes about, and Rerun's archetype constructor
    was a quarter of converting a cube marker."""
    color = _bytes([rgba])
    if marker_type in (CUBE, SPHERE):
        shape = rr.Boxes3D if marker_type == CUBE else rr.Ellipsoids3D
        return (shape(centers=_ORIGIN, half_sizes=[np.array(scale) / 2], colors=color,
                      fill_mode=_SOLID),)
    # Axis along z, height scale.z, diameter scale.x (Rerun cylinders are circular).
    return (rr.Cylinders3D(centers=_ORIGIN, lengths=[scale[2]], radii=[scale[0] / 2], colors=color,
                           fill_mode=_SOLID),)


def _solid_of(marker: Any, ctx: ConvertContext) -> Archetypes:
    return _solid(int(marker.type), _XYZ(marker.scale), _RGBA(marker.color))


def _line_strip(marker: Any, ctx: ConvertContext) -> Archetypes:
    points = _points(marker)
    colors = _point_colors(marker, len(points))
    if len(colors) > 1:
        # Rerun colours whole strips: split into segments, each in its first vertex's colour.
        strips: npt.NDArray[np.float64] = np.stack([points[:-1], points[1:]], axis=1)
        colors = colors[:-1]
    else:
        strips = points[None]
    return (rr.LineStrips3D(strips.astype(np.float32), radii=[_scale(marker)[0] / 2],
                            colors=colors),)


def _line_list(marker: Any, ctx: ConvertContext) -> Archetypes:
    points = _points(marker)
    if len(points) % 2:
        msg = f"LINE_LIST has {len(points)} points; it takes pairs (an even count)"
        raise ConvertError(msg)
    colors = _point_colors(marker, len(points))[::2]
    pairs = points.reshape(-1, 2, 3).astype(np.float32)
    return (rr.LineStrips3D(pairs, radii=[_scale(marker)[0] / 2], colors=colors),)


def _cube_list(marker: Any, ctx: ConvertContext) -> Archetypes:
    points = _points(marker)
    return (rr.Boxes3D(centers=points, half_sizes=[_scale(marker) / 2],
                       colors=_point_colors(marker, len(points)), fill_mode=_SOLID),)


def _sphere_list(marker: Any, ctx: ConvertContext) -> Archetypes:
    points = _points(marker)
    return (rr.Ellipsoids3D(centers=points, half_sizes=[_scale(marker) / 2],
                            colors=_point_colors(marker, len(points)), fill_mode=_SOLID),)


def _points_marker(marker: Any, ctx: ConvertContext) -> Archetypes:
    points = _points(marker)
    return (rr.Points3D(points, radii=[_scale(marker)[0] / 2],
                        colors=_point_colors(marker, len(points))),)


def _text(marker: Any, ctx: ConvertContext) -> Archetypes:
    """A label at the marker origin; Rerun labels have no size, so scale.z is not used."""
    return (rr.Points3D(_ORIGIN, radii=[0.0], labels=[marker.text], show_labels=True,
                        colors=_color(marker)),)


def _triangle_list(marker: Any, ctx: ConvertContext) -> Archetypes:
    points = _points(marker)
    count = len(points)
    if count % 3:
        msg = f"TRIANGLE_LIST has {count} points; it takes whole triangles (a multiple of 3)"
        raise ConvertError(msg)
    vertex_colors: npt.NDArray[np.uint8] | None = None
    if count and len(marker.colors) == count:
        vertex_colors = _rgba8(marker.colors)
    elif count and len(marker.colors) == count // 3:
        vertex_colors = np.repeat(_rgba8(marker.colors), 3, axis=0)
    return (rr.Mesh3D.from_fields(
        clear_unset=True,
        vertex_positions=points * _scale(marker),
        triangle_indices=np.arange(count, dtype=np.uint32).reshape(-1, 3),
        vertex_colors=vertex_colors,
        albedo_factor=_color(marker)[0] if vertex_colors is None else None,
    ),)


def _media_type(name: str) -> Any:
    media_type = rr.components.MediaType.guess_from_path(urlparse(name).path or name)
    if media_type is None:
        msg = f"mesh {name!r}: Rerun reads STL, OBJ, PLY, glTF and GLB; convert the mesh to one"
        raise ConvertError(msg)
    return media_type


def _mesh(marker: Any, ctx: ConvertContext) -> Archetypes:
    uri = marker.mesh_resource
    mesh_file = getattr(marker, "mesh_file", None)  # embedded mesh, ROS 2 Humble and later only
    if uri:
        # Meshes are republished with every marker: read each file once per topic.
        cache = ctx.state(MarkerTopic).meshes
        if uri not in cache:
            media_type = _media_type(uri)
            # package://, file:// and paths, as the robot model's meshes are found.
            cache[uri] = (ctx.robot_state.resolver.read(uri), media_type)
        blob, media_type = cache[uri]
    elif mesh_file is not None and len(mesh_file.data):
        media_type = _media_type(mesh_file.filename)
        blob = np.asarray(mesh_file.data, dtype=np.uint8).tobytes()
    else:
        msg = "MESH_RESOURCE has neither a mesh_resource URI nor mesh_file data"
        raise ConvertError(msg)
    albedo = None if marker.mesh_use_embedded_materials else _color(marker)[0]
    return (
        rr.Asset3D.from_fields(clear_unset=True, blob=blob, media_type=media_type,
                               albedo_factor=albedo),
        # Asset3D has no scale of its own; an instance pose scales the mesh, not the frame.
        rr.InstancePoses3D(scales=[_scale(marker)]),
    )


_BUILDERS: Mapping[int, Callable[[Any, ConvertContext], Archetypes]] = {
    ARROW: _arrow,
    CUBE: _solid_of,
    SPHERE: _solid_of,
    CYLINDER: _solid_of,
    LINE_STRIP: _line_strip,
    LINE_LIST: _line_list,
    CUBE_LIST: _cube_list,
    SPHERE_LIST: _sphere_list,
    POINTS: _points_marker,
    TEXT_VIEW_FACING: _text,
    MESH_RESOURCE: _mesh,
    TRIANGLE_LIST: _triangle_list,
}


def _marker_path(marker: Any, ctx: ConvertContext) -> str:
    """Entity of one marker: ``<topic>/<ns>/<id>``."""
    return ctx.child_path(rr.escape_entity_path_part(marker.ns) if marker.ns else "_",
                          str(int(marker.id)))


def _pose(marker: Any, ctx: ConvertContext) -> rr.Transform3D:
    pose = marker.pose
    return rr.Transform3D(translation=xyz(pose.position),
                          quaternion=rr.Quaternion(xyzw=xyzw(pose.orientation)),
                          parent_frame=ctx.frame(marker.header.frame_id))


def _lifetime_items(path: str, archetypes: Archetypes, lifetime_ns: int,
                    ctx: ConvertContext) -> list[LogItem]:
    """The Clear that ends a marker's lifetime, and a re-log after a stale pending Clear."""
    pending_by_path = ctx.state(MarkerTopic).expiry
    now = ctx.times
    pending = pending_by_path.pop(path, None)
    if pending is not None and any(now[tl] >= t for tl, t in pending.items() if tl in now):
        pending = None  # that Clear is already in the past
    expiry = {tl: t + lifetime_ns for tl, t in now.items()} if lifetime_ns > 0 and now else None
    items: list[LogItem] = []
    if pending is not None and (
        expiry is None or all(expiry[tl] > t for tl, t in pending.items() if tl in expiry)
    ):
        items.append(LogItem(path, archetypes, times={tl: t + 1 for tl, t in pending.items()}))
        pending = None
    if expiry is not None:
        items.append(LogItem(path, (rr.Clear(recursive=False),), times=expiry))
    latest = pending or expiry  # a pending Clear that survived comes after the new one
    if latest:
        pending_by_path[path] = latest
    return items


def _convert_one(marker: Any, ctx: ConvertContext) -> list[LogEntry]:
    types = ctx.state(MarkerTopic).types
    action = int(marker.action)
    if action == DELETEALL:
        types.clear()
        return [LogItem(ctx.entity_path, (rr.Clear(recursive=True),))]
    path = _marker_path(marker, ctx)
    if action == DELETE:
        types.pop(path, None)
        return [LogItem(path, (rr.Clear(recursive=False),))]
    if action != ADD:
        msg = f"action {action} is unknown; use ADD/MODIFY (0), DELETE (2) or DELETEALL (3)"
        raise ConvertError(msg)
    build = _BUILDERS.get(int(marker.type))
    if build is None:
        msg = f"type {marker.type} is unknown; marker types are 0 (ARROW) to 11 (TRIANGLE_LIST)"
        raise ConvertError(msg)
    archetypes = (_pose(marker, ctx), *build(marker, ctx))
    entries: list[LogEntry] = []
    if types.get(path, marker.type) != marker.type:
        # ADD replaces a marker: the previous type's geometry must not linger beside the new one.
        entries.append(LogItem(path, (rr.Clear(recursive=False),)))
    types[path] = int(marker.type)
    entries.append(LogItem(path, archetypes))
    entries.extend(_lifetime_items(path, archetypes, stamp_ns(marker.lifetime), ctx))
    return entries


def _convert_markers(markers: Sequence[Any], ctx: ConvertContext) -> list[LogEntry]:
    entries: list[LogEntry] = []
    problems: list[str] = []
    for marker in markers:
        try:
            entries.extend(_convert_one(marker, ctx))
        except ConvertError as err:
            problems.append(f"{ctx.topic}: marker ns={marker.ns!r} id={marker.id}: {err}")
    if problems and not entries:
        raise ConvertError("; ".join(problems))
    reported = ctx.state(MarkerTopic).reported
    for problem in problems:
        if problem not in reported:
            reported.add(problem)
            entries.append(LogItem(ctx.entity_path,
                                   (rr.TextLog(problem, level=rr.TextLogLevel.WARN),)))
    return entries


def convert_marker(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return _convert_markers([msg], ctx)


def convert_marker_array(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    return _convert_markers(msg.markers, ctx)


MARKER = per_message(convert_marker)
MARKER_ARRAY = per_message(convert_marker_array)
