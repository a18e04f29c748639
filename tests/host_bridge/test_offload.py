"""Heavy topics converted in a process of their own (host_bridge/pipeline/offload.py), logging into the
host's recording at a real Rerun viewer (the ``rerun`` binary saving what it receives)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.destinations import SinkOptions
from host_bridge.outputs.sink import RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.pipeline.offload import HeavyProcess
from host_bridge.table.config import HostConfig
from host_bridge.table.registry import default_registry
from robot_relay.wire import RawMessage
from tests.host_bridge.test_dispatch import grid_cdr
from tests.integration.procs import saving_viewer
from tests.rrd import entity_rows

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
ROBOT = "r"
CLOUD = "sensor_msgs/msg/PointCloud2"
GRID = "nav_msgs/msg/OccupancyGrid"
IMAGE = "sensor_msgs/msg/Image"
STARTUP_S = 60.0
CONFIG = """\
topics:
  /points:
    entity_path: /{robot}/lidar{topic}
    restamp: true
    options: {radius: 0.03}
"""


def cloud_cdr(points: np.ndarray, frame: str) -> bytes:
    """An x, y, z float32 PointCloud2 of ``points`` in ``frame``, stamped 2 s."""
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
              for i, n in enumerate("xyz")]
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=2, nanosec=0), frame_id=frame)
    data = np.ascontiguousarray(points, np.float32).view(np.uint8).ravel()
    cloud = T[CLOUD](header=header, height=1, width=len(points), fields=fields,
                     is_bigendian=False, point_step=12, row_step=12 * len(points), data=data,
                     is_dense=True)
    return bytes(STORE.serialize_cdr(cloud, CLOUD))


def string_cdr(text: str) -> bytes:
    return bytes(STORE.serialize_cdr(T["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


@pytest.fixture
def points() -> np.ndarray:
    return np.arange(300, dtype=np.float32).reshape(100, 3) / 7


def test_heavy_runs_are_converted_in_another_process_into_the_same_recording(
    tmp_path: Path, points: np.ndarray
) -> None:
    received = tmp_path / "viewer.rrd"
    cells = np.zeros((40, 60), np.int8)
    cells[10, 5:50] = 100
    with saving_viewer(received) as (url, _):
        sink = RerunSink(SinkOptions(connect=url))
        assert sink.shared_viewer() == url
        config = tmp_path / "host.yaml"
        config.write_text(CONFIG)
        dispatcher = Dispatcher(sink, strict=True,
                                config=HostConfig.load(config, default_registry()))
        offload = dispatcher.offload = HeavyProcess(dispatcher, url, sink.recording_id)
        dispatcher.take([
            RawMessage(ROBOT, "/points", CLOUD, cloud_cdr(points, "camera"), receive_ns=5),
            RawMessage(ROBOT, "/map", GRID, grid_cdr(cells, 0.05), receive_ns=6),
            RawMessage(ROBOT, "/mode", "std_msgs/msg/String", string_cdr("auto"), receive_ns=7),
        ])
        assert offload.takes(RawMessage(ROBOT, "/points", CLOUD, b""))
        dispatcher.close()
        sink.close()
        assert offload.finish() is None
    counters = {topic: (c.received, c.converted, c.dropped)
                for (_, topic), c in dispatcher.counters.items()}
    assert counters == {"/points": (1, 1, 0), "/map": (1, 1, 0), "/mode": (1, 1, 0)}
    assert dispatcher.counters[(ROBOT, "/points")].convert_seconds > 0
    # Converted in the other process: the grid its update topic would patch is kept there.
    assert dispatcher.robot_state(ROBOT).grids == {}
    # One recording: the host's and the child's rows under the host's recording id.
    assert [r.recording_id for r in RrdReader(received).recordings()] == [sink.recording_id]
    rows = entity_rows(received)
    # The topic's settings from the host configuration, applied in the other process.
    (cloud,) = rows["/r/lidar/points"]
    np.testing.assert_array_equal(np.array(cloud["Points3D:positions"], np.float32), points)
    assert cloud["Points3D:radii"] == [pytest.approx(0.03)]
    assert (cloud["receive_time"], cloud["ros_time"]) == (5, 5)  # restamped
    assert rows["/r/mode"][0]["TextLog:text"] == ["auto"]
    (grid,) = rows["/r/map"]
    assert grid["GridMap:cell_size"] == [pytest.approx(0.05)]
    assert grid["receive_time"] == 6
    # The slow converters run in the child too: the wall along row 10, 45 cells long.
    (walls,) = rows["/r/map/walls"]
    vertices = np.array(walls["Mesh3D:vertex_positions"])
    assert np.ptp(vertices[:, 0]) == pytest.approx(45 * 0.05, abs=0.06)
    # The frames named in the child are placed at the robot's root by the host, and the map
    # frame is the 3D view's target.
    placements = {(r["Transform3D:child_frame"][0], r["Transform3D:parent_frame"][0])
                  for entity in rows.values() for r in entity
                  if r["static"] and r.get("Transform3D:child_frame")}
    assert placements == {("r/camera", "tf#/r"), ("r/map", "tf#/r")}
    assert rows["/r"][-1]["CoordinateFrame:frame"] == ["r/map"]


def test_a_bad_heavy_payload_is_counted_and_warned_by_the_child(
    tmp_path: Path, points: np.ndarray
) -> None:
    with saving_viewer(tmp_path / "viewer.rrd") as (url, _):
        sink = RerunSink(SinkOptions(connect=url))
        dispatcher = Dispatcher(sink)
        offload = dispatcher.offload = HeavyProcess(dispatcher, url, sink.recording_id)
        good = cloud_cdr(points, "camera")
        dispatcher.take([
            RawMessage(ROBOT, "/points", CLOUD, good[:40], receive_ns=1),
            RawMessage(ROBOT, "/points", CLOUD, good, receive_ns=2),
        ])
        dispatcher.close()
        sink.close()
        assert offload.finish() is None
    counters = dispatcher.counters[(ROBOT, "/points")]
    assert (counters.received, counters.converted, counters.dropped, counters.warnings) == (2, 1, 1, 1)


def test_a_heavy_topic_whose_type_changes_is_converted_in_the_child_as_each_type(
    tmp_path: Path, points: np.ndarray
) -> None:
    """An Image, then a PointCloud2 on /points (a sender of garbage, or a node that changed):
    the child gets each type's settings with its first run (it converted the cloud with the
    image's type and options)."""
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="camera")
    image = T[IMAGE](header=header, height=2, width=2, encoding="mono8", is_bigendian=0, step=2,
                     data=np.array([0, 64, 128, 255], np.uint8))
    with saving_viewer(tmp_path / "viewer.rrd") as (url, _):
        sink = RerunSink(SinkOptions(connect=url))
        dispatcher = Dispatcher(sink, strict=True)
        offload = dispatcher.offload = HeavyProcess(dispatcher, url, sink.recording_id)
        dispatcher.take([
            RawMessage(ROBOT, "/points", IMAGE, bytes(STORE.serialize_cdr(image, IMAGE)),
                       receive_ns=1),
            RawMessage(ROBOT, "/points", CLOUD, cloud_cdr(points, "camera"), receive_ns=2),
        ])
        dispatcher.close()
        sink.close()
        assert offload.finish() is None
    counters = dispatcher.counters[(ROBOT, "/points")]
    assert (counters.msgtype, counters.received, counters.converted, counters.dropped,
            counters.warnings) == (CLOUD, 2, 2, 0, 1)
    (cloud,) = [r for r in entity_rows(tmp_path / "viewer.rrd")["/r/points"]
                if "Points3D:positions" in r]
    np.testing.assert_array_equal(np.array(cloud["Points3D:positions"], np.float32), points)


def test_heavy_topics_are_converted_here_once_the_child_is_gone(
    tmp_path: Path, points: np.ndarray, caplog: pytest.LogCaptureFixture
) -> None:
    with saving_viewer(tmp_path / "viewer.rrd") as (url, _):
        sink = RerunSink(SinkOptions(connect=url))
        dispatcher = Dispatcher(sink, strict=True)
        offload = dispatcher.offload = HeavyProcess(dispatcher, url, sink.recording_id)
        cloud = RawMessage(ROBOT, "/points", CLOUD, cloud_cdr(points, "camera"), receive_ns=1)
        dispatcher.take([cloud])
        offload._process.kill()
        with caplog.at_level(logging.WARNING):
            dispatcher.take([cloud, cloud])
        assert not offload.takes(cloud)
        dispatcher.take([cloud])
        dispatcher.close()
        sink.close()
        assert offload.finish() is None
    counters = dispatcher.counters[(ROBOT, "/points")]
    assert (counters.received, counters.converted, counters.dropped) == (4, 4, 0)
    assert dispatcher.robot_state(ROBOT).grids == {}
    warned = [r.getMessage() for r in caplog.records if "converter process" in r.getMessage()]
    assert len(warned) == 1
    assert "/points" in warned[0]
    assert "exited (code -9)" in warned[0] or "stopped answering" in warned[0]


def test_only_a_viewer_of_its_own_is_shared_with_another_process(tmp_path: Path) -> None:
    """A --save file (and the --serve-web server) belong to the host's process."""
    sink = RerunSink(SinkOptions(save=tmp_path / "out.rrd"))
    assert sink.shared_viewer() is None
    sink.close()
