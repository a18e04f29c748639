"""TF, LaserScan, Odometry and the generic fallback: values Rerun receives."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters.generic import convert_generic
from host_bridge.converters.laser import convert_scan
from host_bridge.converters.odometry import SPEC as ODOMETRY
from host_bridge.converters.tf import SPEC as TF
from host_bridge.core.contract import ColumnsItem, ConvertContext, LogItem
from host_bridge.core.options import Options
from host_bridge.core.state import TopicState
from host_bridge.table.registry import Row, default_registry
from tests.host_bridge.sensor_test_support import convert, convert_run, default_message, make_ctx

T = get_typestore(Stores.ROS2_HUMBLE).types


def ctx(topic: str, robot: str = "tb3", **options: Any) -> ConvertContext:
    return make_ctx(topic, options, robot=robot, times={"ros_time": 5, "log_time": 6})


def header(frame: str, ns: int = 0) -> Any:
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def transform(parent: str, child: str, x: float, yaw: float, ns: int) -> Any:
    return T["geometry_msgs/msg/TransformStamped"](
        header=header(parent, ns),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=0.0, z=0.0),
            rotation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        ),
    )


def column(item: ColumnsItem, name: str) -> list[Any]:
    for col in item.columns:
        if col.component_descriptor().component == name:
            return list(col.as_arrow_array().to_pylist())
    raise KeyError(name)


def scan(ranges: list[float]) -> Any:
    return T["sensor_msgs/msg/LaserScan"](
        header=header("laser", 7), angle_min=0.0, angle_max=math.pi,
        angle_increment=math.pi / 2, time_increment=0.0, scan_time=0.1, range_min=0.1,
        range_max=10.0, ranges=np.array(ranges, dtype=np.float32),
        intensities=np.array([], dtype=np.float32),
    )


def test_dynamic_tf_is_one_row_per_transform_with_prefixed_frames_and_own_stamps() -> None:
    msg = T["tf2_msgs/msg/TFMessage"](transforms=[
        transform("odom", "base_link", 1.5, math.pi / 2, 10),
        transform("/base_link", "wheel", 0.1, 0.0, 20),
    ])
    [item] = convert(TF, msg, ctx("/tf"))
    assert isinstance(item, ColumnsItem)
    assert item.path == "/tb3/tf"
    assert column(item, "Transform3D:parent_frame") == [["tb3/odom"], ["tb3/base_link"]]
    assert column(item, "Transform3D:child_frame") == [["tb3/base_link"], ["tb3/wheel"]]
    assert column(item, "Transform3D:translation")[0] == [[1.5, 0.0, 0.0]]
    qx, qy, qz, qw = column(item, "Transform3D:quaternion")[0][0]
    assert (qx, qy) == (0.0, 0.0)
    assert qz == pytest.approx(math.sqrt(0.5))
    assert qw == pytest.approx(math.sqrt(0.5))
    assert item.times["ros_time"].tolist() == [10, 20]
    assert item.times["log_time"].tolist() == [6, 6]


def test_tf_runs_concatenate_and_two_robots_never_share_frames() -> None:
    one = T["tf2_msgs/msg/TFMessage"](transforms=[transform("odom", "base_link", 1.0, 0, 1)])
    [item] = convert_run(TF, [one, one], [ctx("/tf", "tb1"), ctx("/tf", "tb1")])
    assert isinstance(item, ColumnsItem)
    assert len(item.times["ros_time"]) == 2
    [other] = convert(TF, one, ctx("/tf", "tb2"))
    assert isinstance(other, ColumnsItem)
    assert column(other, "Transform3D:child_frame") == [["tb2/base_link"]]


def test_static_tf_is_static_one_entity_per_child_frame() -> None:
    msg = T["tf2_msgs/msg/TFMessage"](transforms=[
        transform("base_link", "laser", 0.2, 0.0, 0), transform("base_link", "imu", 0.0, 0.0, 0),
    ])
    state = ctx("/tf_static")
    items = convert(TF, msg, state)
    assert [i.path for i in items] == ["/tb3/tf_static/laser", "/tb3/tf_static/imu"]
    assert all(isinstance(i, LogItem) and i.static for i in items)
    assert state.robot_state.tf_children == {"laser", "imu"}


def test_laser_points_drop_invalid_returns_and_sit_in_the_scan_frame() -> None:
    items = convert_scan(scan([1.0, float("nan"), 2.0, 50.0]), ctx("/scan"))
    [points] = items
    assert isinstance(points, LogItem)
    positions = points.archetypes[0].positions.as_arrow_array().to_pylist()  # type: ignore[attr-defined]
    np.testing.assert_allclose(positions, [[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]], atol=1e-6)
    frame = points.archetypes[1].frame.as_arrow_array().to_pylist()  # type: ignore[attr-defined]
    assert frame == ["tb3/laser"]


def test_laser_rays_mode_draws_segments_from_the_sensor() -> None:
    items = convert_scan(scan([1.0, 1.0, 1.0, 1.0]), ctx("/scan", mode="both"))
    assert [i.path for i in items] == ["/tb3/scan", "/tb3/scan/rays"]
    rays = items[1]
    assert isinstance(rays, LogItem)
    strips = rays.archetypes[0].strips.as_arrow_array().to_pylist()  # type: ignore[attr-defined]
    assert len(strips) == 4
    np.testing.assert_allclose(strips[1], [[0, 0, 0], [0, 1, 0]], atol=1e-6)


def test_odometry_pose_twist_and_trail() -> None:
    def odom(x: float, stamp_s: int) -> Any:
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=2.0, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        twist = T["geometry_msgs/msg/Twist"](
            linear=T["geometry_msgs/msg/Vector3"](x=0.3, y=0.0, z=0.0),
            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.5),
        )
        return T["nav_msgs/msg/Odometry"](
            header=header("odom", stamp_s * 1_000_000_000), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )

    c = ctx("/odom")
    items = convert_run(ODOMETRY, [odom(0.0, 1), odom(0.001, 2), odom(1.0, 3)], [c, c, c])
    by_path = {i.path: i for i in items if isinstance(i, ColumnsItem)}
    pose = by_path["/tb3/odom"]
    assert column(pose, "Transform3D:translation")[2] == [[1.0, 2.0, 0.0]]
    assert column(pose, "Transform3D:parent_frame")[0] == ["tb3/odom"]
    assert column(by_path["/tb3/odom/twist/linear"], "Scalars:scalars") == [[0.3, 0.0, 0.0]] * 3
    assert column(by_path["/tb3/odom/twist/angular"], "Scalars:scalars") == [[0.0, 0.0, 0.5]] * 3
    [trail] = [i for i in items if i.path == "/tb3/odom/trail"]
    assert isinstance(trail, ColumnsItem)
    # The 1 mm step is below the trail's minimum step: the trail grows at x=0 and x=1 only.
    strips = column(trail, "LineStrips3D:strips")
    assert strips[-1] == [[[0.0, 2.0, 0.0], [1.0, 2.0, 0.0]]]
    assert len(strips) == 2


def test_generic_fallback_plots_numbers_and_logs_text() -> None:
    msg = T["sensor_msgs/msg/BatteryState"](
        header=header("bat"), voltage=12.5, temperature=30.0, current=-1.0, charge=1.0,
        capacity=2.0, design_capacity=2.0, percentage=0.5, power_supply_status=2,
        power_supply_health=1, power_supply_technology=3, present=True,
        cell_voltage=np.array([4.1, 4.2], dtype=np.float32),
        cell_temperature=np.array([], dtype=np.float32), location="slot", serial_number="A1",
    )
    items = {i.path: i for i in convert(convert_generic, msg, ctx("/battery"))}
    assert "/tb3/battery/header" not in items
    voltage = items["/tb3/battery/voltage"]
    assert isinstance(voltage, ColumnsItem)
    assert column(voltage, "Scalars:scalars") == [[12.5]]
    assert column(items["/tb3/battery/present"], "Scalars:scalars") == [[1.0]]  # type: ignore[arg-type]
    cells = column(items["/tb3/battery/cell_voltage"], "Scalars:scalars")  # type: ignore[arg-type]
    np.testing.assert_allclose(cells, [[4.1, 4.2]], rtol=1e-6)
    assert column(items["/tb3/battery/location"], "TextLog:text") == [["slot"]]  # type: ignore[arg-type]


TABLE = default_registry()


class AskedOptions(TopicState):
    """A topic's state that notes which options records the converters ask for."""

    __slots__ = ("asked",)

    def __init__(self, options: dict[str, Any]) -> None:
        super().__init__(options)
        self.asked: set[type[Any]] = set()

    def options(self, kind: type[Options], topic: str) -> Options:
        self.asked.add(kind)
        return super().options(kind, topic)


@pytest.mark.parametrize(
    "row",
    [row for row in TABLE.rows() if not row.is_family],
    ids=lambda row: row.msgtype + (" (by topic)" if row.topics else ""),
)
def test_every_registered_type_has_a_converter_that_handles_a_default_message(row: Row) -> None:
    """Walks the type table: each row's converter (and its slow one) accepts a
    default-constructed message of its type (or refuses it with a ConvertError, never another
    exception), and reads its options as the row's record, the one the configuration checks a
    file against (given every option of it, as a config may set them all)."""
    from host_bridge.core.schemas import base_typestore
    from host_bridge.errors import ConvertError

    store = base_typestore()
    if row.msgtype not in store.types:
        pytest.skip(f"{row.msgtype} is a ROS 1 type (only ROS 1 bags carry it)")
    topic = "/robot_description" if row.topics is not None else "/topic"
    assert TABLE.row(row.msgtype, topic) is row
    msg = default_message(store, row.msgtype)
    topic_state = AskedOptions(dataclasses.asdict(row.options()))
    context = make_ctx(topic, robot="tb3", times={"ros_time": 5, "log_time": 6}, topic_state=topic_state)
    for converter in (row.converter, row.slow):
        if converter is None:
            continue
        try:
            entries = convert(converter, msg, context)
        except ConvertError:
            continue
        assert all(e.path.startswith("/tb3/") for e in entries)
    assert topic_state.asked <= {row.options}
