"""The error policy: a bad message is reported once, named, and nothing else is lost."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.destinations import SinkOptions
from host_bridge.errors import DecodeError
from host_bridge.outputs.sink import RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from robot_relay.wire import MessageDefinition, RawMessage
from tests.rrd import entity_rows

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types


def string_cdr(text: str) -> bytes:
    return bytes(STORE.serialize_cdr(T["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


def float_cdr(value: float) -> bytes:
    return bytes(STORE.serialize_cdr(T["std_msgs/msg/Float64"](data=value), "std_msgs/msg/Float64"))


def grid_cdr(cells: np.ndarray, resolution: float) -> bytes:
    """A /map OccupancyGrid at the origin, stamped 1 s."""
    height, width = cells.shape
    info = T["nav_msgs/msg/MapMetaData"](
        map_load_time=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), resolution=resolution,
        width=width, height=height,
        origin=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
    )
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="map"
    )
    grid = T["nav_msgs/msg/OccupancyGrid"](header=header, info=info, data=cells.ravel())
    return bytes(STORE.serialize_cdr(grid, "nav_msgs/msg/OccupancyGrid"))


TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
SECOND = 1_000_000_000


def stamp(ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=ns // SECOND, nanosec=ns % SECOND)


def twist(forward: float) -> Any:
    vector = T["geometry_msgs/msg/Vector3"]
    return T[TWIST](linear=vector(x=forward, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.5))


def twist_cdr(forward: float) -> bytes:
    """A /cmd_vel Twist as Humble's nav2 sends it: ``forward`` m/s, turning at 0.5 rad/s."""
    return bytes(STORE.serialize_cdr(twist(forward), TWIST))


def twist_stamped_cdr(forward: float, ns: int) -> bytes:
    """The same command as Jazzy's nav2 sends it, stamped ``ns`` in frame base_link."""
    header = T["std_msgs/msg/Header"](stamp=stamp(ns), frame_id="base_link")
    return bytes(STORE.serialize_cdr(T[TWIST_STAMPED](header=header, twist=twist(forward)),
                                     TWIST_STAMPED))


def scan_cdr(ranges: list[float], ns: int) -> bytes:
    """A LaserScan of quarter turns from angle 0 in frame laser, stamped ``ns``."""
    scan = T[LASER_SCAN](
        header=T["std_msgs/msg/Header"](stamp=stamp(ns), frame_id="laser"),
        angle_min=0.0, angle_max=1.5 * np.pi, angle_increment=0.5 * np.pi, time_increment=0.0,
        scan_time=0.1, range_min=0.1, range_max=10.0,
        ranges=np.array(ranges, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32),
    )
    return bytes(STORE.serialize_cdr(scan, LASER_SCAN))


def raw(topic: str, msgtype: str, data: bytes, ns: int, **kw: object) -> RawMessage:
    return RawMessage("tb3", topic, msgtype, data, log_ns=ns, **kw)  # type: ignore[arg-type]


@pytest.fixture
def dispatcher(tmp_path: Path) -> Dispatcher:
    return Dispatcher(RerunSink(SinkOptions(save=tmp_path / "out.rrd")))


def test_truncated_cdr_is_warned_once_naming_the_topic_and_others_flow(
    dispatcher: Dispatcher, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    good = float_cdr(1.5)
    batch = [
        raw("/speed", "std_msgs/msg/Float64", good, 1),
        raw("/speed", "std_msgs/msg/Float64", good[:6], 2),
        raw("/speed", "std_msgs/msg/Float64", good[:5], 3),
        raw("/speed", "std_msgs/msg/Float64", good, 4),
        raw("/mode", "std_msgs/msg/String", string_cdr("auto"), 5),
    ]
    with caplog.at_level(logging.WARNING):
        dispatcher.dispatch(batch)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1
    assert "/speed" in warnings[0]
    assert "std_msgs/msg/Float64" in warnings[0]
    counters = dispatcher.counters[("tb3", "/speed")]
    assert (counters.received, counters.converted, counters.dropped) == (4, 2, 2)
    dispatcher.sink.close()
    rows = entity_rows(tmp_path / "out.rrd")
    assert [r["Scalars:scalars"] for r in rows["/tb3/speed"]] == [[1.5], [1.5]]
    assert rows["/tb3/mode"][0]["TextLog:text"] == ["auto"]
    assert "/speed" in rows["/_swanky/warnings"][0]["TextLog:text"][0]


def test_unknown_type_without_definition_names_type_and_topic(
    dispatcher: Dispatcher, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        dispatcher.dispatch([
            raw("/custom", "my_pkg/msg/Thing", b"\x00\x01\x00\x00", 1),
            raw("/mode", "std_msgs/msg/String", string_cdr("ok"), 2),
        ])
    [warning] = [r.getMessage() for r in caplog.records]
    assert "/custom" in warning
    assert "my_pkg/msg/Thing" in warning
    assert dispatcher.counters[("tb3", "/mode")].converted == 1


def test_custom_type_decodes_from_the_definition_it_came_with(dispatcher: Dispatcher) -> None:
    text = "float64 speed\nstring label\n"
    custom = get_typestore(Stores.EMPTY)
    from rosbags.typesys import get_types_from_msg

    custom.register(get_types_from_msg(text, "my_pkg/msg/Thing"))
    data = custom.serialize_cdr(custom.types["my_pkg/msg/Thing"](speed=2.5, label="x"),
                                "my_pkg/msg/Thing")
    message = raw("/custom", "my_pkg/msg/Thing", bytes(data), 1,
                  definition=MessageDefinition("ros2msg", text))
    dispatcher.dispatch([message])
    assert dispatcher.counters[("tb3", "/custom")].converted == 1


def test_strict_mode_re_raises(tmp_path: Path) -> None:
    strict = Dispatcher(RerunSink(SinkOptions(save=tmp_path / "s.rrd")), strict=True)
    with pytest.raises(DecodeError, match="std_msgs/msg/Float64 payload does not deserialize"):
        strict.dispatch([raw("/speed", "std_msgs/msg/Float64", b"\x00\x01", 1)])


def test_sequence_gaps_count_as_drops(dispatcher: Dispatcher) -> None:
    data = float_cdr(1.0)
    dispatcher.dispatch([raw("/s", "std_msgs/msg/Float64", data, i, sequence=i) for i in (0, 1, 4)])
    assert dispatcher.counters[("tb3", "/s")].sequence_gaps == 2


def test_wall_meshes_are_built_off_the_receive_path_and_land_in_the_recording(
    dispatcher: Dispatcher, tmp_path: Path
) -> None:
    """A map goes through the fast GridMap converter at once; its walls come from the slow
    worker, and closing the dispatcher waits for them."""

    cells = np.zeros((60, 60), dtype=np.int8)
    cells[10, 10:50] = 100  # a 2 m wall along x at y = 0.5 m
    cells[10:50, 10] = 100  # and one along y: an L corner
    data = grid_cdr(cells, 0.05)
    dispatcher.dispatch([raw("/map", "nav_msgs/msg/OccupancyGrid", data, 1)])
    dispatcher.close()
    dispatcher.sink.close()
    rows = entity_rows(tmp_path / "out.rrd")
    assert rows["/tb3/map"][0]["GridMap:cell_size"] == [pytest.approx(0.05)]
    vertices = np.asarray(rows["/tb3/map/walls"][-1]["Mesh3D:vertex_positions"])
    assert len(vertices) == 2 * 24  # two walls, one box each
    assert vertices[:, 0].max() == pytest.approx(2.5, abs=0.1)
    assert vertices[:, 1].max() == pytest.approx(2.5, abs=0.1)
    assert rows["/tb3/map/walls"][-1]["ros_time"] == 1_000_000_000


def test_warnings_keep_their_time_and_a_rejected_map_is_warned_once(
    dispatcher: Dispatcher, tmp_path: Path
) -> None:
    """Two different warnings both stay in the recording (a static row would replace the one
    before), each at its message's time; a map the GridMap converter rejects (resolution 0, as
    in ros_numpy's bag) is not handed on to the wall builder to be warned about again."""
    dispatcher.dispatch([
        raw("/map", "nav_msgs/msg/OccupancyGrid", grid_cdr(np.zeros((2, 2), dtype=np.int8), 0.0), 7),
        raw("/speed", "std_msgs/msg/Float64", float_cdr(1.0)[:5], 9),
    ])
    dispatcher.close()
    dispatcher.sink.close()
    assert dispatcher.counters[("tb3", "/map")].warnings == 1
    warnings = sorted(entity_rows(tmp_path / "out.rrd")["/_swanky/warnings"], key=lambda w: w["log_time"])
    assert [(w["static"], w["log_time"]) for w in warnings] == [(False, 7), (False, 9)]
    assert ["/map" in w["TextLog:text"][0] for w in warnings] == [True, False]


def test_a_warning_names_its_topic_once(
    dispatcher: Dispatcher, caplog: pytest.LogCaptureFixture
) -> None:
    """Converters put the topic into their errors (a --strict run ends with just that text);
    the warning does not repeat it (it read ``/occupancygrid: /occupancygrid: ...``)."""
    grid = grid_cdr(np.zeros((2, 2), dtype=np.int8), 0.0)
    with caplog.at_level(logging.WARNING):
        dispatcher.dispatch([
            raw("/occupancygrid", "nav_msgs/msg/OccupancyGrid", grid, 1),
            raw("/speed", "std_msgs/msg/Float64", float_cdr(1.0)[:5], 2),
        ])
    occupancy, speed = (r.getMessage() for r in caplog.records)
    assert occupancy.startswith("[tb3] /occupancygrid: ")
    assert occupancy.count("/occupancygrid") == 1
    assert occupancy.endswith(" (further ConvertErrors on this topic are counted, not shown)")
    assert "\n" not in occupancy
    # A decoder error does not name the topic itself: the warning adds it, once.
    assert speed.startswith("[tb3] /speed: ")
    assert speed.count("/speed") == 1


def test_a_topic_whose_type_changes_is_drawn_as_each_type_with_one_warning(
    dispatcher: Dispatcher, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Jazzy's Twist -> TwistStamped on /cmd_vel while the robot stays: the batch in which the
    type changes converts each message as its own type (its first TwistStamped ones were drawn
    as Twist fields under /cmd_vel/twist), and later batches with TwistStamped's converter."""
    times = [(i + 1) * SECOND for i in range(8)]
    dispatcher.dispatch([raw("/cmd_vel", TWIST, twist_cdr(i), times[i]) for i in range(3)])
    with caplog.at_level(logging.WARNING):
        dispatcher.dispatch([
            raw("/cmd_vel", TWIST, twist_cdr(3), times[3]),
            *(raw("/cmd_vel", TWIST_STAMPED, twist_stamped_cdr(i, times[i]), times[i])
              for i in (4, 5)),
        ])
        dispatcher.dispatch([raw("/cmd_vel", TWIST_STAMPED, twist_stamped_cdr(i, times[i]), times[i])
                             for i in (6, 7)])
    assert [r.getMessage() for r in caplog.records] == [
        "[tb3] /cmd_vel: type changed from geometry_msgs/msg/Twist to "
        "geometry_msgs/msg/TwistStamped; each message is converted as its own type, with that "
        "type's options (further TypeChangeErrors on this topic are counted, not shown)"
    ]
    counters = dispatcher.counters[("tb3", "/cmd_vel")]
    assert (counters.msgtype, counters.received, counters.converted, counters.dropped,
            counters.warnings) == (TWIST_STAMPED, 8, 8, 0, 1)
    dispatcher.sink.close()
    rows = entity_rows(tmp_path / "out.rrd")
    # Both types' vectors on the same plots (an x, y and z series each), the Twist's without a
    # header time.
    linear = [r for r in rows["/tb3/cmd_vel/linear"] if "Scalars:scalars" in r]
    assert [r["Scalars:scalars"] for r in linear] == [[float(i), 0.0, 0.0] for i in range(8)]
    assert [r.get("ros_time") for r in linear] == [None] * 4 + times[4:]
    angular = [r["Scalars:scalars"] for r in rows["/tb3/cmd_vel/angular"] if "Scalars:scalars" in r]
    assert angular == [[0.0, 0.0, 0.5]] * 8
    arrows = [r for r in rows["/tb3/cmd_vel"] if r.get("Arrows3D:vectors")]
    assert [(r["ros_time"], r["Arrows3D:vectors"]) for r in arrows] == [
        (times[i], [[float(i), 0.0, 0.0], [0.0, 0.0, 0.5]]) for i in (4, 5, 6, 7)
    ]
    assert not [path for path in rows if path.startswith("/tb3/cmd_vel/twist")]


def test_messages_of_another_type_never_change_how_a_topics_messages_convert(
    dispatcher: Dispatcher, tmp_path: Path
) -> None:
    """Garbage on /scan: a Twist first (its generic converter's options, max_array, made every
    later scan fail: 'LaserScanOptions takes no option max_array'), then a batch that starts
    with a cut PointCloud2 (its converter took the scans behind it: 'LaserScan object has no
    attribute data'), then scans alone. Every scan is drawn, point for point."""
    times = [(i + 1) * SECOND for i in range(6)]
    dispatcher.dispatch([raw("/scan", TWIST, twist_cdr(1.0), times[0])])
    dispatcher.dispatch([raw("/scan", LASER_SCAN, scan_cdr([1.0, 2.0, 3.0, 4.0], times[1]), times[1])])
    dispatcher.dispatch([
        raw("/scan", "sensor_msgs/msg/PointCloud2", scan_cdr([1.0], times[2])[:9], times[2]),
        raw("/scan", LASER_SCAN, scan_cdr([2.0, 2.0, 2.0, 2.0], times[3]), times[3]),
        raw("/scan", LASER_SCAN, scan_cdr([1.0, 20.0, 1.0, 0.05], times[4]), times[4]),
        raw("/scan", TWIST, twist_cdr(2.0), times[5]),
    ])
    counters = dispatcher.counters[("tb3", "/scan")]
    # The cut PointCloud2 alone is lost; 4 type changes and it counted in the warnings.
    assert (counters.received, counters.converted, counters.dropped) == (6, 5, 1)
    assert (counters.msgtype, counters.warnings) == (TWIST, 4 + 1)
    dispatcher.sink.close()
    scans = [r for r in entity_rows(tmp_path / "out.rrd")["/tb3/scan"] if "Points3D:positions" in r]
    assert [r["ros_time"] for r in scans] == [times[1], times[3], times[4]]
    expected = [
        [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [-3.0, 0.0, 0.0], [0.0, -4.0, 0.0]],
        [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [-2.0, 0.0, 0.0], [0.0, -2.0, 0.0]],
        [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],  # 20 m is beyond range_max, 5 cm short of range_min
    ]
    for row, points in zip(scans, expected, strict=True):
        np.testing.assert_allclose(row["Points3D:positions"], points, atol=1e-6)
