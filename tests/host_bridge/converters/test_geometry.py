"""geometry_msgs converters: the values Rerun receives (poses, trails, ellipsoids, arrows)."""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters.geometry import (
    POINT,
    POLYGON,
    POSE_ARRAY,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE,
    TWIST,
    VECTOR3,
    WRENCH,
)
from host_bridge.core.contract import ColumnsItem, ConvertContext, LogEntry, LogItem
from host_bridge.core.state import TopicState
from tests.host_bridge.sensor_test_support import TYPES as T
from tests.host_bridge.sensor_test_support import archetype, convert, convert_run, header, log_item, make_ctx

NS = 1_000_000_000


def _vec(xyz: Sequence[float], kind: str = "Vector3") -> Any:
    x, y, z = xyz
    return T[f"geometry_msgs/msg/{kind}"](x=x, y=y, z=z)


def _pose(position: Sequence[float], xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> Any:
    x, y, z, w = xyzw
    return T["geometry_msgs/msg/Pose"](
        position=_vec(position, kind="Point"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
    )


def _pose_stamped(position: Sequence[float], frame_id: str = "map", ns: int = 0) -> Any:
    return T["geometry_msgs/msg/PoseStamped"](header=header(frame_id, ns), pose=_pose(position))


def _ctx(
    topic: str = "/goal",
    ns: int = 0,
    state: TopicState | None = None,
    options: dict[str, Any] | None = None,
) -> ConvertContext:
    return make_ctx(topic, options, ns, robot="tb3", topic_state=state)


def _at(entries: Sequence[LogEntry], path: str) -> list[LogEntry]:
    return [e for e in entries if e.path == path]


def _scalars(entries: Sequence[LogEntry], path: str) -> ColumnsItem:
    """The one columns item of a plot at ``path`` (its legends, a static LogItem, left out)."""
    (item,) = [e for e in entries if e.path == path and isinstance(e, ColumnsItem)]
    return item


def _column(item: LogEntry, component: str) -> list[Any] | None:
    """Rows of one component column ("Transform3D:translation"); None when it was not sent."""
    assert isinstance(item, ColumnsItem)
    for column in item.columns:
        if column.component_descriptor().component == component:
            return list(column.as_arrow_array().to_pylist())
    return None


def _values(batch: Any) -> npt.NDArray[np.float64]:
    return np.array(batch.as_arrow_array().to_pylist(), dtype=np.float64)


def _trail_rows(entries: Sequence[LogEntry], path: str = "/tb3/goal/trail") -> list[Any]:
    trail = _at(entries, path)
    return [] if not trail else _column(trail[0], "LineStrips3D:strips") or []


# --- PoseStamped -----------------------------------------------------------------------------


def test_pose_stamped_is_a_transform_under_the_header_frame() -> None:
    msg = T["geometry_msgs/msg/PoseStamped"](
        header=header("map", 5 * NS + 7),
        pose=_pose((1.0, 2.0, 3.0), (0.1, 0.2, 0.3, 0.9)),
    )
    entries = convert(POSE_STAMPED, msg, _ctx(ns=5 * NS + 7))
    (pose,) = _at(entries, "/tb3/goal")
    assert _column(pose, "Transform3D:translation") == [[[1.0, 2.0, 3.0]]]
    quaternion = _column(pose, "Transform3D:quaternion")
    assert quaternion is not None
    np.testing.assert_allclose(quaternion[0][0], [0.1, 0.2, 0.3, 0.9], rtol=1e-6)  # xyzw
    assert _column(pose, "Transform3D:parent_frame") == [["tb3/map"]]
    assert _column(pose, "Transform3D:child_frame") is None  # never collides with /tf
    assert _column(pose, "CoordinateFrame:frame") is None  # the entity IS the pose frame
    assert _column(pose, "TransformAxes3D:axis_length") == [[pytest.approx(0.3)]]
    assert isinstance(pose, ColumnsItem)
    assert pose.times["ros_time"].tolist() == [5 * NS + 7]
    (trail,) = _at(entries, "/tb3/goal/trail")
    assert _column(trail, "LineStrips3D:strips") == [[[[1.0, 2.0, 3.0]]]]
    assert _column(trail, "CoordinateFrame:frame") == [["tb3/map"]]


def test_pose_stamped_with_empty_frame_has_no_frame_names() -> None:
    entries = convert(POSE_STAMPED, _pose_stamped((1.0, 0.0, 0.0), frame_id=""), _ctx())
    (pose,) = _at(entries, "/tb3/goal")
    assert _column(pose, "Transform3D:parent_frame") is None
    assert _column(pose, "CoordinateFrame:frame") is None
    # The trail sits in the pose's (implicit) parent frame, so it does not ride on the pose.
    (trail,) = _at(entries, "/tb3/goal/trail")
    assert _column(trail, "CoordinateFrame:frame") == [["tf#/tb3"]]


def test_all_zero_quaternion_becomes_identity() -> None:
    msg = T["geometry_msgs/msg/PoseStamped"](
        header=header("map"),
        pose=_pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0)),
    )
    (pose, _) = convert(POSE_STAMPED, msg, _ctx())
    assert _column(pose, "Transform3D:quaternion") == [[[0.0, 0.0, 0.0, 1.0]]]


def test_trail_grows_only_when_the_pose_moved_more_than_1cm() -> None:
    state = TopicState()
    xs = [0.0, 0.005, 0.0105, 0.019, 0.5, 0.5]
    grown = [
        _trail_rows(convert(POSE_STAMPED, _pose_stamped((x, 0.0, 0.0)), _ctx(state=state)))
        for x in xs
    ]
    assert [len(rows) for rows in grown] == [1, 0, 1, 0, 1, 0]
    last = np.array(grown[4][0][0])
    np.testing.assert_allclose(last[:, 0], [0.0, 0.0105, 0.5])


def test_trail_keeps_the_last_trail_length_points_and_restarts_on_frame_change() -> None:
    state = TopicState({"trail_length": 3})
    for x in range(5):
        entries = convert(POSE_STAMPED, _pose_stamped((float(x), 0.0, 0.0)), _ctx(state=state))
    assert np.array(_trail_rows(entries)[0][0])[:, 0].tolist() == [2.0, 3.0, 4.0]
    entries = convert(POSE_STAMPED,
        _pose_stamped((9.0, 0.0, 0.0), frame_id="odom"), _ctx(state=state)
    )
    (trail,) = _at(entries, "/tb3/goal/trail")
    assert _column(trail, "LineStrips3D:strips") == [[[[9.0, 0.0, 0.0]]]]
    assert _column(trail, "CoordinateFrame:frame") == [["tb3/odom"]]


def test_trail_rows_are_a_trail_period_apart_by_stamp_and_keep_every_point() -> None:
    # 30 Hz poses moving 5 cm each: a trail row every 0.1 s (default), every point in the trail.
    state = TopicState()
    ms = 1_000_000
    stamps = [10 * NS + i * 33 * ms for i in range(10)]
    msgs = [_pose_stamped((0.05 * i, 0.0, 0.0), "map", stamp) for i, stamp in enumerate(stamps)]
    entries = convert_run(POSE_STAMPED, msgs, [_ctx(ns=stamp, state=state) for stamp in stamps])
    (trail,) = _at(entries, "/tb3/goal/trail")
    assert isinstance(trail, ColumnsItem)
    assert trail.times["ros_time"].tolist() == [stamps[0], stamps[4], stamps[8]]
    strips = _column(trail, "LineStrips3D:strips")
    assert strips is not None
    assert [len(strip[0]) for strip in strips] == [1, 5, 9]
    # The next run goes on from the last row shown, message by message as a live topic arrives.
    shown = [
        _trail_rows(convert(POSE_STAMPED, _pose_stamped((0.05 * i, 0.0, 0.0), "map", stamp),
                            _ctx(ns=stamp, state=state)))
        for i, stamp in ((10, stamps[0] + 370 * ms), (11, stamps[0] + 400 * ms))
    ]
    assert [len(rows) for rows in shown] == [1, 0]
    assert len(shown[0][0][0]) == 11
    # A stamp earlier than the last row's (a bag looped), another frame, or no stamp: shown.
    for position, frame, stamp in (((5.0, 0, 0), "map", NS), ((6.0, 0, 0), "odom", NS + ms),
                                   ((7.0, 0, 0), "odom", 0), ((8.0, 0, 0), "odom", 0)):
        assert len(_trail_rows(convert(POSE_STAMPED, _pose_stamped(position, frame, stamp),
                                       _ctx(ns=stamp, state=state)))) == 1


def test_trail_period_zero_logs_a_trail_row_for_every_move() -> None:
    state = TopicState({"trail_period": 0.0})
    stamps = [NS + i * 1_000_000 for i in range(4)]
    msgs = [_pose_stamped((0.05 * i, 0.0, 0.0), "map", stamp) for i, stamp in enumerate(stamps)]
    entries = convert_run(POSE_STAMPED, msgs, [_ctx(ns=stamp, state=state) for stamp in stamps])
    (trail,) = _at(entries, "/tb3/goal/trail")
    assert isinstance(trail, ColumnsItem)
    assert trail.times["ros_time"].tolist() == stamps


def test_trail_length_zero_disables_the_trail() -> None:
    entries = convert(POSE_STAMPED,
        _pose_stamped((1.0, 0.0, 0.0)),
        _ctx(options={"trail_length": 0}),
    )
    assert [e.path for e in entries] == ["/tb3/goal"]


def test_pose_run_splits_rows_by_frame_and_stamps_trail_rows() -> None:
    frames = ("map", "", "", "map")
    msgs = [
        _pose_stamped((x, 0.0, 0.0), frame, i * NS)
        for i, (x, frame) in enumerate(zip((0.0, 1.0, 1.001, 2.0), frames, strict=True), start=1)
    ]
    state = TopicState()
    ctxs = [_ctx(ns=i * NS, state=state) for i in range(1, len(msgs) + 1)]
    entries = convert_run(POSE_STAMPED, msgs, ctxs)
    with_frame, without_frame = _at(entries, "/tb3/goal")
    assert isinstance(with_frame, ColumnsItem)
    assert isinstance(without_frame, ColumnsItem)
    assert with_frame.times["ros_time"].tolist() == [NS, 4 * NS]
    assert _column(with_frame, "Transform3D:parent_frame") == [["tb3/map"], ["tb3/map"]]
    assert without_frame.times["ros_time"].tolist() == [2 * NS, 3 * NS]
    assert _column(without_frame, "Transform3D:parent_frame") is None
    (trail,) = _at(entries, "/tb3/goal/trail")
    assert isinstance(trail, ColumnsItem)
    # The frame changes twice (trail restarts), the 1 mm step is ignored.
    assert trail.times["ros_time"].tolist() == [NS, 2 * NS, 4 * NS]
    assert _column(trail, "CoordinateFrame:frame") == [["tb3/map"], ["tf#/tb3"], ["tb3/map"]]
    assert _column(trail, "LineStrips3D:strips") == [
        [[[0.0, 0.0, 0.0]]],
        [[[1.0, 0.0, 0.0]]],
        [[[2.0, 0.0, 0.0]]],
    ]


# --- PoseWithCovarianceStamped ---------------------------------------------------------------


def _with_covariance(position: Sequence[float], cov3: npt.NDArray[np.float64]) -> Any:
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = cov3
    covariance[3:, 3:] = np.eye(3) * 7.0  # orientation part: must not leak into the ellipsoid
    inner = T["geometry_msgs/msg/PoseWithCovariance"](
        pose=_pose(position),
        covariance=covariance.ravel(),
    )
    return T["geometry_msgs/msg/PoseWithCovarianceStamped"](header=header("map"), pose=inner)


def _ellipsoid(entries: Sequence[LogEntry], path: str = "/tb3/goal/covariance") -> Any:
    """The one message's ellipsoid: its columns' single row, as Ellipsoids3D would hold it."""
    (item,) = _at(entries, path)
    assert _column(item, "CoordinateFrame:frame") == [["tb3/map"]]
    rows = {
        name: (_column(item, f"Ellipsoids3D:{name}") or [None])[0]
        for name in ("centers", "half_sizes", "quaternions")
    }
    return rr.Ellipsoids3D(**rows)


def _rotation(xyzw: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    x, y, z, w = xyzw / np.linalg.norm(xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
    )


def test_diagonal_covariance_gives_sqrt_half_sizes_and_no_rotation() -> None:
    spec = POSE_WITH_COVARIANCE
    msg = _with_covariance((1.0, 2.0, 0.0), np.diag([4.0, 1.0, 0.25]))
    entries = convert(spec, msg, _ctx())
    ellipsoid = _ellipsoid(entries)
    np.testing.assert_allclose(_values(ellipsoid.half_sizes), [[2.0, 1.0, 0.5]], rtol=1e-6)
    np.testing.assert_allclose(_values(ellipsoid.centers), [[1.0, 2.0, 0.0]])
    np.testing.assert_allclose(np.abs(_values(ellipsoid.quaternions)), [[0, 0, 0, 1]], atol=1e-7)
    # The pose itself is there too, with its trail.
    assert [e.path for e in entries] == ["/tb3/goal", "/tb3/goal/trail", "/tb3/goal/covariance"]
    doubled = _ellipsoid(convert(spec, msg, _ctx(options={"sigma": 2.0})))
    np.testing.assert_allclose(_values(doubled.half_sizes), [[4.0, 2.0, 1.0]], rtol=1e-6)


def test_rotated_covariance_ellipsoid_reproduces_the_covariance() -> None:
    yaw, roll = math.radians(30.0), math.radians(-50.0)
    cy, sy, cr, sr = math.cos(yaw), math.sin(yaw), math.cos(roll), math.sin(roll)
    axes = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array(
        [[1, 0, 0], [0, cr, -sr], [0, sr, cr]],
    )
    cov = axes @ np.diag([9.0, 4.0, 1.0]) @ axes.T
    spec = POSE_WITH_COVARIANCE
    ellipsoid = _ellipsoid(convert(spec, _with_covariance((0.0, 0.0, 0.0), cov), _ctx()))
    half = _values(ellipsoid.half_sizes)[0]
    np.testing.assert_allclose(half, [3.0, 2.0, 1.0], rtol=1e-5)
    rotation = _rotation(_values(ellipsoid.quaternions)[0])
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-6)
    np.testing.assert_allclose(rotation @ np.diag(half**2) @ rotation.T, cov, atol=1e-5)
    # The longest axis (3 sigma) points along the first rotated axis, up to sign.
    np.testing.assert_allclose(np.abs(rotation[:, 0]), np.abs(axes[:, 0]), atol=1e-6)


def test_non_finite_covariance_keeps_the_pose_without_ellipsoid() -> None:
    spec = POSE_WITH_COVARIANCE
    entries = convert(spec, _with_covariance((1.0, 0.0, 0.0), np.full((3, 3), np.nan)), _ctx())
    assert [e.path for e in entries] == ["/tb3/goal", "/tb3/goal/trail"]


# --- PoseArray, vectors, points, polygons ----------------------------------------------------


def test_pose_array_draws_one_arrow_along_each_x_axis() -> None:
    half = math.sqrt(0.5)
    msg = T["geometry_msgs/msg/PoseArray"](
        header=header("map"),
        # identity, yaw +90 degrees, and the invalid all-zero quaternion (drawn as identity)
        poses=[
            _pose((0, 0, 0)),
            _pose((1, 2, 0), (0, 0, half, half)),
            _pose((0, 0, 1), (0, 0, 0, 0)),
        ],
    )
    spec = POSE_ARRAY
    item = log_item(spec.convert(msg, _ctx(options={"arrow_length": 2.0})), "/tb3/goal")
    arrows = archetype(item, rr.Arrows3D)
    np.testing.assert_allclose(_values(arrows.origins), [[0, 0, 0], [1, 2, 0], [0, 0, 1]])
    np.testing.assert_allclose(
        _values(arrows.vectors),
        [[2, 0, 0], [0, 2, 0], [2, 0, 0]],
        atol=1e-6,
    )
    assert archetype(item, rr.CoordinateFrame).frame.as_arrow_array().to_pylist() == ["tb3/map"]


def _twist(linear: Sequence[float], angular: Sequence[float], frame_id: str = "base_link") -> Any:
    twist = T["geometry_msgs/msg/Twist"](linear=_vec(linear), angular=_vec(angular))
    return T["geometry_msgs/msg/TwistStamped"](header=header(frame_id), twist=twist)


def test_twist_stamped_arrows_and_per_component_scalars() -> None:
    spec = TWIST
    entries = convert(spec, _twist((0.5, 0.0, 0.0), (0.0, 0.0, -0.25)), _ctx("/cmd"))
    (arrows,) = _at(entries, "/tb3/cmd")
    frame = arrows
    assert _column(arrows, "Arrows3D:vectors") == [[[0.5, 0.0, 0.0], [0.0, 0.0, -0.25]]]
    assert _column(arrows, "Arrows3D:origins") == [[[0.0, 0.0, 0.0]] * 2]
    assert _column(arrows, "Arrows3D:labels") == [["linear", "angular"]]
    assert _column(frame, "CoordinateFrame:frame") == [["tb3/base_link"]]
    plots = [e for e in entries if e.path != "/tb3/cmd"]
    scalars = {e.path: _column(e, "Scalars:scalars") for e in plots if isinstance(e, ColumnsItem)}
    # One plot per vector, an x, y and z series each, named once.
    assert scalars == {"/tb3/cmd/linear": [[0.5, 0.0, 0.0]], "/tb3/cmd/angular": [[0.0, 0.0, -0.25]]}
    legends = {e.path: archetype(e, rr.SeriesLines).names.as_arrow_array().to_pylist()
               for e in plots if isinstance(e, LogItem) and e.static}
    assert legends == {path: ["x", "y", "z"] for path in scalars}


def test_wrench_and_vector3_use_their_field_names() -> None:
    wrench = T["geometry_msgs/msg/WrenchStamped"](
        header=header(""),
        wrench=T["geometry_msgs/msg/Wrench"](force=_vec((1, 2, 3)), torque=_vec((4, 5, 6))),
    )
    entries = convert(WRENCH, wrench, _ctx("/ft"))
    (arrows,) = _at(entries, "/tb3/ft")  # empty frame_id: no CoordinateFrame item
    assert _column(arrows, "Arrows3D:vectors") == [[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]]
    assert _column(_scalars(entries, "/tb3/ft/torque"), "Scalars:scalars") == [[4.0, 5.0, 6.0]]
    vector = T["geometry_msgs/msg/Vector3Stamped"](header=header("imu"), vector=_vec((0, -9.8, 0)))
    entries = convert(VECTOR3, vector, _ctx("/g"))
    assert _column(_at(entries, "/tb3/g")[0], "Arrows3D:labels") == [["vector"]]
    assert _column(_scalars(entries, "/tb3/g/vector"), "Scalars:scalars") == [
        [0.0, pytest.approx(-9.8), 0.0]]


def test_point_stamped_and_closed_polygon() -> None:
    point = T["geometry_msgs/msg/PointStamped"](
        header=header("map"),
        point=_vec((1, 2, 3), "Point"),
    )
    point_spec = POINT
    item = log_item(point_spec.convert(point, _ctx("/clicked")), "/tb3/clicked")
    np.testing.assert_allclose(_values(archetype(item, rr.Points3D).positions), [[1, 2, 3]])
    square = [_vec((x, y, 0.0), "Point32") for x, y in [(0, 0), (1, 0), (1, 1), (0, 1)]]
    polygon = T["geometry_msgs/msg/PolygonStamped"](
        header=header("base_link"),
        polygon=T["geometry_msgs/msg/Polygon"](points=square),
    )
    polygon_spec = POLYGON
    item = log_item(polygon_spec.convert(polygon, _ctx("/footprint")), "/tb3/footprint")
    strips = archetype(item, rr.LineStrips3D).strips.as_arrow_array().to_pylist()
    assert strips == [[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]]]
    assert archetype(item, rr.CoordinateFrame).frame.as_arrow_array().to_pylist() == [
        "tb3/base_link",
    ]
    empty = T["geometry_msgs/msg/PolygonStamped"](
        header=header("base_link"),
        polygon=T["geometry_msgs/msg/Polygon"](points=[]),
    )
    item = log_item(polygon_spec.convert(empty, _ctx("/footprint")), "/tb3/footprint")
    assert archetype(item, rr.LineStrips3D).strips.as_arrow_array().to_pylist() == []


# --- the real bag: /location (empty frame_id) and /velocity, through the run forms ----------


@pytest.fixture(scope="module")
def amr_bag(shared_data: Path) -> dict[str, list[tuple[int, Any]]]:
    """/location and /velocity of the TurtleBot3 nav bag: topic -> [(log_time ns, msg)]."""
    path = shared_data / "tb3_nav_sim_paths_amr" / "rosbag_demo.bag"
    by_topic: dict[str, list[tuple[int, Any]]] = {"/location": [], "/velocity": []}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        connections = [c for c in reader.connections if c.topic in by_topic]
        for conn, log_ns, raw in reader.messages(connections=connections):
            by_topic[conn.topic].append((log_ns, reader.deserialize(raw, conn.msgtype)))
    return by_topic


def _bag_ctxs(topic: str, rows: list[tuple[int, Any]]) -> list[ConvertContext]:
    state = TopicState()
    return [
        make_ctx(
            topic,
            robot="tb3",
            topic_state=state,
            times={
                "ros_time": int(m.header.stamp.sec) * NS + int(m.header.stamp.nanosec),
                "log_time": log_ns,
            },
        )
        for log_ns, m in rows
    ]


def _send(entries: Sequence[LogEntry]) -> None:
    """Hand everything to a real (in-memory) recording, as the sink will."""
    recording = rr.RecordingStream("swanky_test_geometry")
    recording.memory_recording()
    for entry in entries:
        if isinstance(entry, LogItem):  # a plot's legends
            rr.log(entry.path, *entry.archetypes, static=entry.static, recording=recording)
            continue
        assert isinstance(entry, ColumnsItem)
        indexes = [
            rr.TimeColumn(name, timestamp=values.astype("datetime64[ns]"))
            for name, values in entry.times.items()
        ]
        rr.send_columns(entry.path, indexes=indexes, columns=entry.columns, recording=recording)


def test_real_location_and_velocity_convert_as_runs(
    amr_bag: dict[str, list[tuple[int, Any]]],
) -> None:
    location, velocity = amr_bag["/location"], amr_bag["/velocity"]
    assert (len(location), len(velocity)) == (5273, 5270)
    started = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        poses = convert_run(POSE_STAMPED, [m for _, m in location], _bag_ctxs("/location", location))
        twists = convert_run(TWIST, [m for _, m in velocity], _bag_ctxs("/velocity", velocity))
        _send([*poses, *twists])
    assert time.perf_counter() - started < 10.0  # run forms; per message takes ~8 s here

    # /location: empty frame_id -> one row group, no frame names, translation as recorded.
    (pose,) = _at(poses, "/tb3/location")
    assert isinstance(pose, ColumnsItem)
    assert _column(pose, "Transform3D:parent_frame") is None
    expected = np.array(
        [(m.pose.position.x, m.pose.position.y, m.pose.position.z) for _, m in location],
        dtype=np.float32,
    )
    translation = _column(pose, "Transform3D:translation")
    assert translation is not None
    np.testing.assert_array_equal(np.array(translation, dtype=np.float32)[:, 0], expected)
    assert pose.times["log_time"].tolist() == [log_ns for log_ns, _ in location]

    (trail,) = _at(poses, "/tb3/location/trail")
    strips = _column(trail, "LineStrips3D:strips")
    assert strips is not None
    assert 0 < len(strips) < len(location)
    final = np.array(strips[-1][0])
    assert 1 < len(final) <= 500
    assert (np.linalg.norm(np.diff(final, axis=0), axis=1) > 0.01).all()
    assert _column(trail, "CoordinateFrame:frame") == [["tf#/tb3"]] * len(strips)

    # /velocity: every component plotted, one row per message; no CoordinateFrame (empty id).
    values = _column(_scalars(twists, "/tb3/velocity/linear"), "Scalars:scalars")
    assert values is not None
    np.testing.assert_array_equal(
        np.array(values),
        [[m.twist.linear.x, m.twist.linear.y, m.twist.linear.z] for _, m in velocity],
    )
    arrows = _at(twists, "/tb3/velocity")
    assert len(arrows) == 1
    vectors = _column(arrows[0], "Arrows3D:vectors")
    assert vectors is not None
    assert len(vectors) == 5270
    assert all(len(row) == 2 for row in vectors)
    assert len(twists) == 1 + 2 + 2  # the arrows, two plots, their legends
