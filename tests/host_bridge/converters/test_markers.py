"""Marker / MarkerArray: the geometry, poses, colours, deletes and lifetimes Rerun receives."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr

from host_bridge.converters import markers
from host_bridge.core.contract import ConvertContext, LogEntry, LogItem
from host_bridge.core.resources import ResourceResolver
from host_bridge.core.state import RobotState, TopicState
from host_bridge.errors import ConvertError
from tests.host_bridge.sensor_test_support import ROBOT, archetype, header, log_item, make_ctx, msg

TOPIC = "/viz"
BASE = f"/{ROBOT}{TOPIC}"
LDS = Path("turtlebot3_description/turtlebot3_description/meshes/sensors/lds.stl")


def values(batch: Any) -> list[Any]:
    return list(batch.pa_array.to_pylist())


def rgba(batch: Any) -> list[tuple[int, ...]]:
    """Rerun's packed 0xRRGGBBAA colours back as RGBA tuples."""
    return [tuple(int(c).to_bytes(4, "big")) for c in values(batch)]


def point(x: float, y: float, z: float = 0.0) -> Any:
    return msg("geometry_msgs/msg/Point", x=x, y=y, z=z)


def color(r: float, g: float, b: float, a: float = 1.0) -> Any:
    return msg("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=a)


def marker(
    kind: int = markers.CUBE,
    *,
    ns: str = "ns",
    marker_id: int = 0,
    action: int = markers.ADD,
    frame_id: str = "map",
    position: tuple[float, float, float] = (0.0, 0.0, 0.0),
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0),
    rgba: Any = None,
    points: list[Any] | None = None,
    colors: list[Any] | None = None,
    text: str = "",
    mesh_resource: str = "",
    lifetime_ns: int = 0,
    embedded: bool = False,
) -> Any:
    qx, qy, qz, qw = orientation
    return msg(
        "visualization_msgs/msg/Marker",
        header=header(frame_id),
        ns=ns,
        id=marker_id,
        type=kind,
        action=action,
        pose=msg(
            "geometry_msgs/msg/Pose",
            position=point(*position),
            orientation=msg("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw),
        ),
        scale=msg("geometry_msgs/msg/Vector3", x=scale[0], y=scale[1], z=scale[2]),
        color=rgba or color(1.0, 0.0, 0.0),
        lifetime=msg(
            "builtin_interfaces/msg/Duration",
            sec=lifetime_ns // 1_000_000_000,
            nanosec=lifetime_ns % 1_000_000_000,
        ),
        frame_locked=False,
        points=points or [],
        colors=colors or [],
        texture_resource="",
        texture=msg(
            "sensor_msgs/msg/CompressedImage",
            header=header(),
            format="",
            data=np.zeros(0, np.uint8),
        ),
        uv_coordinates=[],
        text=text,
        mesh_resource=mesh_resource,
        mesh_file=msg("visualization_msgs/msg/MeshFile", filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=embedded,
    )


def array(*items: Any) -> Any:
    return msg("visualization_msgs/msg/MarkerArray", markers=list(items))


def convert(m: Any, ctx: ConvertContext | None = None) -> list[LogEntry]:
    return markers.convert_marker(m, ctx or make_ctx(TOPIC))


def rotate(q: list[float], v: list[float]) -> np.ndarray[Any, Any]:
    """Rotate v by the xyzw quaternion q."""
    x, y, z, w = q
    u = np.array([x, y, z])
    vec = np.asarray(v, dtype=np.float64)
    return vec + 2.0 * np.cross(u, np.cross(u, vec) + w * vec)


def test_cube_pose_size_and_frame() -> None:
    item = log_item(
        convert(
            marker(
                markers.CUBE,
                ns="obstacles",
                marker_id=7,
                position=(1.0, 2.0, 3.0),
                scale=(1.0, 2.0, 4.0),
            )
        ),
        f"{BASE}/obstacles/7",
    )
    transform = archetype(item, rr.Transform3D)
    assert values(transform.translation) == [[1.0, 2.0, 3.0]]
    assert values(transform.quaternion) == [[0.0, 0.0, 0.0, 1.0]]
    assert values(transform.parent_frame) == [f"{ROBOT}/map"]
    assert transform.child_frame is None  # the entity's implicit frame
    assert transform.scale is None  # scale lives in the geometry
    box = archetype(item, rr.Boxes3D)
    assert values(box.half_sizes) == [[0.5, 1.0, 2.0]]
    assert values(box.centers) == [[0.0, 0.0, 0.0]]
    assert rgba(box.colors) == [(255, 0, 0, 255)]


def test_sphere_and_cylinder_sizes() -> None:
    sphere = archetype(
        log_item(convert(marker(markers.SPHERE, scale=(0.2, 0.4, 0.6))), f"{BASE}/ns/0"),
        rr.Ellipsoids3D,
    )
    assert np.allclose(values(sphere.half_sizes), [[0.1, 0.2, 0.3]])
    assert values(sphere.centers) == [[0.0, 0.0, 0.0]]
    cylinder = archetype(
        log_item(convert(marker(markers.CYLINDER, scale=(0.5, 0.5, 2.0))), f"{BASE}/ns/0"),
        rr.Cylinders3D,
    )
    assert values(cylinder.lengths) == [2.0]
    assert values(cylinder.radii) == [0.25]
    assert values(cylinder.centers) == [[0.0, 0.0, 0.0]]


def test_rotated_arrow_points_along_rotated_x() -> None:
    half = math.sqrt(0.5)  # 90 degrees about z
    item = log_item(
        convert(
            marker(
                markers.ARROW,
                orientation=(0.0, 0.0, half, half),
                position=(1.0, 0.0, 0.0),
                scale=(2.0, 0.1, 0.2),
            )
        ),
        f"{BASE}/ns/0",
    )
    arrow = archetype(item, rr.Arrows3D)
    assert np.allclose(values(arrow.vectors), [[2.0, 0.0, 0.0]])
    assert np.allclose(values(arrow.radii), [0.05])
    quaternion = values(archetype(item, rr.Transform3D).quaternion)[0]
    assert np.allclose(rotate(quaternion, values(arrow.vectors)[0]), [0.0, 2.0, 0.0], atol=1e-6)


def test_arrow_from_two_points() -> None:
    m = marker(markers.ARROW, points=[point(1.0, 1.0), point(1.0, 3.0, 1.0)], scale=(0.2, 0.4, 0))
    arrow = archetype(log_item(convert(m), f"{BASE}/ns/0"), rr.Arrows3D)
    assert values(arrow.origins) == [[1.0, 1.0, 0.0]]
    assert values(arrow.vectors) == [[0.0, 2.0, 1.0]]
    assert np.allclose(values(arrow.radii), [0.1])


def test_line_list_pairs_with_first_point_colours() -> None:
    pts = [point(0, 0), point(1, 0), point(0, 1), point(1, 1)]
    cols = [color(1, 0, 0), color(0, 1, 0), color(0, 0, 1), color(1, 1, 1)]
    m = marker(markers.LINE_LIST, points=pts, colors=cols, scale=(0.1, 0, 0))
    lines = archetype(log_item(convert(m), f"{BASE}/ns/0"), rr.LineStrips3D)
    assert values(lines.strips) == [[[0, 0, 0], [1, 0, 0]], [[0, 1, 0], [1, 1, 0]]]
    assert rgba(lines.colors) == [(255, 0, 0, 255), (0, 0, 255, 255)]
    assert np.allclose(values(lines.radii), [0.05])


def test_line_list_with_odd_count_is_refused() -> None:
    m = marker(markers.LINE_LIST, points=[point(0, 0), point(1, 0), point(2, 0)])
    with pytest.raises(ConvertError, match=r"/viz.*ns='ns' id=0.*even"):
        convert(m)


def test_line_strip_single_colour_and_per_vertex_colours() -> None:
    pts = [point(0, 0), point(1, 0), point(1, 1)]
    strip = archetype(
        log_item(convert(marker(markers.LINE_STRIP, points=pts)), f"{BASE}/ns/0"), rr.LineStrips3D
    )
    assert values(strip.strips) == [[[0, 0, 0], [1, 0, 0], [1, 1, 0]]]
    cols = [color(1, 0, 0), color(0, 1, 0), color(0, 0, 1)]
    m = marker(markers.LINE_STRIP, points=pts, colors=cols)
    segments = archetype(log_item(convert(m), f"{BASE}/ns/0"), rr.LineStrips3D)
    assert values(segments.strips) == [[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [1, 1, 0]]]
    assert rgba(segments.colors) == [(255, 0, 0, 255), (0, 255, 0, 255)]


def test_points_with_per_point_colours() -> None:
    pts = [point(1, 2, 3), point(4, 5, 6)]
    cols = [color(0.5, 0.25, 0.0, 1.0), color(0.0, 1.0, 1.0, 0.5)]
    m = marker(markers.POINTS, points=pts, colors=cols, scale=(0.04, 0.04, 0))
    cloud = archetype(log_item(convert(m), f"{BASE}/ns/0"), rr.Points3D)
    assert values(cloud.positions) == [[1, 2, 3], [4, 5, 6]]
    assert rgba(cloud.colors) == [(128, 64, 0, 255), (0, 255, 255, 128)]
    assert np.allclose(values(cloud.radii), [0.02])


def test_cube_and_sphere_lists() -> None:
    pts = [point(1, 0), point(2, 0)]
    m = marker(markers.CUBE_LIST, points=pts, scale=(0.2, 0.2, 0.2))
    cubes = archetype(log_item(convert(m), f"{BASE}/ns/0"), rr.Boxes3D)
    assert values(cubes.centers) == [[1, 0, 0], [2, 0, 0]]
    assert np.allclose(values(cubes.half_sizes), [[0.1, 0.1, 0.1]])
    spheres = archetype(
        log_item(convert(marker(markers.SPHERE_LIST, points=pts)), f"{BASE}/ns/0"), rr.Ellipsoids3D
    )
    assert values(spheres.centers) == [[1, 0, 0], [2, 0, 0]]
    assert rgba(spheres.colors) == [(255, 0, 0, 255)]  # the marker colour splats


def test_text_label() -> None:
    label = archetype(
        log_item(convert(marker(markers.TEXT_VIEW_FACING, text="dock")), f"{BASE}/ns/0"),
        rr.Points3D,
    )
    assert values(label.labels) == ["dock"]
    assert values(label.show_labels) == [True]
    assert values(label.positions) == [[0, 0, 0]]


def test_triangle_list_vertices_indices_and_face_colours() -> None:
    pts = [point(0, 0), point(1, 0), point(0, 1), point(1, 1), point(2, 1), point(1, 2)]
    m = marker(
        markers.TRIANGLE_LIST,
        points=pts,
        scale=(2.0, 2.0, 2.0),
        colors=[color(1, 0, 0), color(0, 0, 1)],
    )
    mesh = archetype(log_item(convert(m), f"{BASE}/ns/0"), rr.Mesh3D)
    assert len(values(mesh.vertex_positions)) == 6
    assert values(mesh.vertex_positions)[4] == [4.0, 2.0, 0.0]  # scaled
    assert values(mesh.triangle_indices) == [[0, 1, 2], [3, 4, 5]]
    assert rgba(mesh.vertex_colors) == [(255, 0, 0, 255)] * 3 + [(0, 0, 255, 255)] * 3
    assert values(mesh.albedo_factor) == []  # cleared: vertex colours rule


def test_triangle_list_with_partial_triangle_is_refused() -> None:
    with pytest.raises(ConvertError, match="multiple of 3"):
        convert(marker(markers.TRIANGLE_LIST, points=[point(0, 0), point(1, 0)]))


def test_mesh_resource_from_local_stl(shared_data: Path) -> None:
    stl = shared_data / LDS
    m = marker(markers.MESH_RESOURCE, mesh_resource=stl.as_uri(), scale=(0.001, 0.001, 0.001))
    item = log_item(convert(m), f"{BASE}/ns/0")
    asset = archetype(item, rr.Asset3D)
    assert values(asset.media_type) == ["model/stl"]
    assert bytes(values(asset.blob)[0]) == stl.read_bytes()
    assert rgba(asset.albedo_factor) == [(255, 0, 0, 255)]
    assert np.allclose(values(archetype(item, rr.InstancePoses3D).scales), [[0.001] * 3])


def test_package_uri_goes_through_the_robot_resolver(shared_data: Path) -> None:
    uri = "package://turtlebot3_description/meshes/sensors/lds.stl"
    resolver = ResourceResolver(search_paths=[shared_data / "turtlebot3_description"])
    ctx = make_ctx(TOPIC, robot_state=RobotState(resolver))
    asset = archetype(
        log_item(
            convert(marker(markers.MESH_RESOURCE, mesh_resource=uri, embedded=True), ctx),
            f"{BASE}/ns/0",
        ),
        rr.Asset3D,
    )
    assert len(values(asset.blob)[0]) == (shared_data / LDS).stat().st_size
    assert values(asset.albedo_factor) == []  # embedded materials keep their colours


def test_unresolvable_mesh_skips_only_that_marker() -> None:
    uri = "package://robot/meshes/base.stl"
    with pytest.raises(ConvertError, match=r"package://robot/meshes/base\.stl"):
        convert(marker(markers.MESH_RESOURCE, mesh_resource=uri))
    ctx = make_ctx(TOPIC)
    both = array(
        marker(markers.MESH_RESOURCE, mesh_resource=uri, marker_id=1),
        marker(markers.CUBE, marker_id=2),
    )
    entries = markers.convert_marker_array(both, ctx)
    assert archetype(log_item(entries, f"{BASE}/ns/2"), rr.Boxes3D) is not None
    warning = archetype(log_item(entries, BASE), rr.TextLog)
    assert "package://robot/meshes/base.stl" in values(warning.text)[0]
    again = markers.convert_marker_array(both, ctx)  # reported once per topic
    assert [e.path for e in again if isinstance(e, LogItem)] == [f"{BASE}/ns/2"]


def test_delete_clears_only_that_marker() -> None:
    ctx = make_ctx(TOPIC)
    markers.convert_marker(marker(marker_id=3), ctx)
    entries = markers.convert_marker(marker(marker_id=3, action=markers.DELETE), ctx)
    clear = archetype(log_item(entries, f"{BASE}/ns/3"), rr.Clear)
    assert values(clear.is_recursive) == [False]
    assert ctx.state(markers.MarkerTopic).types == {}


def test_deleteall_clears_the_topic_then_later_markers_show() -> None:
    ctx = make_ctx(TOPIC)
    markers.convert_marker_array(array(marker(ns="a", marker_id=1), marker(ns="b")), ctx)
    assert set(ctx.state(markers.MarkerTopic).types) == {f"{BASE}/a/1", f"{BASE}/b/0"}
    entries = markers.convert_marker_array(
        array(marker(action=markers.DELETEALL), marker(ns="c", marker_id=5)), ctx
    )
    assert [e.path for e in entries if isinstance(e, LogItem)] == [BASE, f"{BASE}/c/5"]
    assert values(archetype(log_item(entries, BASE), rr.Clear).is_recursive) == [True]
    assert set(ctx.state(markers.MarkerTopic).types) == {f"{BASE}/c/5"}


def test_type_change_clears_the_old_geometry_first() -> None:
    ctx = make_ctx(TOPIC)
    markers.convert_marker(marker(markers.CUBE), ctx)
    entries = markers.convert_marker(marker(markers.SPHERE), ctx)
    assert isinstance(entries[0], LogItem)
    assert [type(a) for a in entries[0].archetypes] == [rr.Clear]
    assert any(isinstance(a, rr.Ellipsoids3D) for a in entries[1].archetypes)  # type: ignore[union-attr]


def test_namespace_is_escaped_and_empty_frame_has_no_parent() -> None:
    item = log_item(
        convert(marker(ns="arm/links 2", marker_id=-1, frame_id="")), f"{BASE}/arm\\/links\\ 2/-1"
    )
    assert archetype(item, rr.Transform3D).parent_frame is None
    assert log_item(convert(marker(ns="")), f"{BASE}/_/0") is not None


def _timed_ctx(t_ns: int, state: TopicState) -> ConvertContext:
    return make_ctx(TOPIC, topic_state=state, times={"ros_time": t_ns, "receive_time": t_ns + 5_000})


def _clears(entries: list[LogEntry], path: str) -> list[LogItem]:
    return [
        e
        for e in entries
        if isinstance(e, LogItem)
        and e.path == path
        and any(isinstance(a, rr.Clear) for a in e.archetypes)
    ]


def test_lifetime_adds_a_clear_at_stamp_plus_lifetime_on_every_timeline() -> None:
    ctx = _timed_ctx(10_000_000_000, TopicState())
    entries = markers.convert_marker(marker(lifetime_ns=1_500_000_000), ctx)
    (clear,) = _clears(entries, f"{BASE}/ns/0")
    assert clear.times == {"ros_time": 11_500_000_000, "receive_time": 11_500_005_000}
    assert not _clears(markers.convert_marker(marker(marker_id=1), ctx), f"{BASE}/ns/1")


def test_republished_marker_is_relogged_after_the_stale_clear() -> None:
    state = TopicState()
    markers.convert_marker(marker(lifetime_ns=1_000_000_000), _timed_ctx(0, state))
    entries = markers.convert_marker(
        marker(lifetime_ns=1_000_000_000), _timed_ctx(500_000_000, state)
    )
    path = f"{BASE}/ns/0"
    timed = [e for e in entries if isinstance(e, LogItem) and e.path == path and e.times]
    relog, clear = timed
    assert relog.times == {"ros_time": 1_000_000_001, "receive_time": 1_000_005_001}
    assert any(isinstance(a, rr.Boxes3D) for a in relog.archetypes)
    assert clear.times == {"ros_time": 1_500_000_000, "receive_time": 1_500_005_000}
    # Once the first Clear has passed, nothing is re-logged.
    later = markers.convert_marker(
        marker(lifetime_ns=1_000_000_000), _timed_ctx(2_000_000_000, state)
    )
    assert [e.times for e in later if isinstance(e, LogItem) and e.times] == [
        {"ros_time": 3_000_000_000, "receive_time": 3_000_005_000}
    ]
