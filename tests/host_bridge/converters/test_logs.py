"""Text converters: /rosout levels and text (ROS 2 and ROS 1), std_msgs/String."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from rosbags.typesys import Stores, get_typestore

from host_bridge.converters.logs import ROS1_LOG, ROS2_LOG, STRING
from host_bridge.core.contract import ColumnsItem, ConvertContext, LogEntry, PerMessage
from tests.host_bridge.sensor_test_support import TYPES as ROS2
from tests.host_bridge.sensor_test_support import convert, convert_run, make_ctx, read_topic

ROS1 = get_typestore(Stores.ROS1_NOETIC).types
NS = 1_000_000_000


def _ctx(topic: str = "/rosout", ns: int = 0) -> ConvertContext:
    return make_ctx(topic, robot="tb3", times={"ros_time": ns, "receive_time": ns + 1})


def _rows(item: LogEntry) -> dict[str, list[Any]]:
    """Component -> one value per row (each row holds a single log line)."""
    assert isinstance(item, ColumnsItem)
    rows = {}
    for column in item.columns:
        values = column.as_arrow_array().to_pylist()
        assert all(len(row) == 1 for row in values)
        rows[column.component_descriptor().component] = [row[0] for row in values]
    return rows


def _ros2_log(level: int, name: str = "talker", text: str = "hello", ns: int = 0) -> Any:
    stamp = ROS2["builtin_interfaces/msg/Time"](sec=ns // NS, nanosec=ns % NS)
    return ROS2["rcl_interfaces/msg/Log"](
        stamp=stamp,
        level=level,
        name=name,
        msg=text,
        file="talker.cpp",
        function="main",
        line=42,
    )


def _ros1_log(level: int, name: str = "/talker", text: str = "hello") -> Any:
    header = ROS1["std_msgs/msg/Header"](
        seq=3,
        stamp=ROS1["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
        frame_id="",
    )
    return ROS1["rosgraph_msgs/msg/Log"](
        header=header,
        level=level,
        name=name,
        msg=text,
        file="talker.py",
        function="main",
        line=7,
        topics=["/chatter"],
    )


@pytest.mark.parametrize(
    ("level", "expected"),
    [
        (10, "DEBUG"),
        (20, "INFO"),
        (30, "WARN"),
        (40, "ERROR"),
        (50, "CRITICAL"),
        (0, "TRACE"),  # UNSET
        (25, "INFO"),  # in between rounds down
    ],
)
def test_ros2_log_levels_and_text(level: int, expected: str) -> None:
    (item,) = convert(
        ROS2_LOG,
        _ros2_log(level, "talker", "Publishing: 'Hello World: 1'", ns=7 * NS + 5),
        _ctx(ns=99),
    )
    assert item.path == "/tb3/rosout"
    rows = _rows(item)
    assert rows["TextLog:level"] == [expected]
    assert rows["TextLog:text"] == ["[talker] Publishing: 'Hello World: 1'"]
    assert isinstance(item, ColumnsItem)
    # rcl_interfaces/Log has no header: its own stamp is the message time.
    assert item.times["ros_time"].tolist() == [7 * NS + 5]
    assert item.times["receive_time"].tolist() == [100]


@pytest.mark.parametrize(
    ("level", "expected"),
    [(1, "DEBUG"), (2, "INFO"), (4, "WARN"), (8, "ERROR"), (16, "CRITICAL"), (0, "TRACE")],
)
def test_ros1_log_levels(level: int, expected: str) -> None:
    (item,) = convert(ROS1_LOG, _ros1_log(level), _ctx(ns=5))
    rows = _rows(item)
    assert rows["TextLog:level"] == [expected]
    assert rows["TextLog:text"] == ["[/talker] hello"]
    assert isinstance(item, ColumnsItem)
    assert item.times["ros_time"].tolist() == [NS]  # its header stamp


def test_rosout_run_is_one_column_with_a_row_per_line() -> None:
    spec = ROS2_LOG
    assert not isinstance(spec, PerMessage)
    msgs = [
        _ros2_log(level, f"node{level}", f"line {level}", ns=level * NS)
        for level in (20, 30, 40, 10)
    ]
    (item,) = convert_run(spec, msgs, [_ctx(ns=i) for i in range(len(msgs))])
    rows = _rows(item)
    assert rows["TextLog:level"] == ["INFO", "WARN", "ERROR", "DEBUG"]
    assert rows["TextLog:text"] == [
        "[node20] line 20",
        "[node30] line 30",
        "[node40] line 40",
        "[node10] line 10",
    ]
    assert isinstance(item, ColumnsItem)
    assert item.times["ros_time"].tolist() == [20 * NS, 30 * NS, 40 * NS, 10 * NS]
    assert item.times["receive_time"].tolist() == [1, 2, 3, 4]


@pytest.mark.parametrize(
    ("topic", "count", "first"),
    [("/mode", 5, "charging"), ("/troubleshooting/errorcodes", 37, "error_194,error_1")],
)
def test_real_string_topics_become_info_lines(
    shared_data: Path, topic: str, count: int, first: str,
) -> None:
    run = list(read_topic(shared_data / "tb3_nav_sim_paths_amr" / "rosbag_demo.bag", topic))
    assert len(run) == count
    spec = STRING
    assert not isinstance(spec, PerMessage)
    (item,) = convert_run(spec, run, [_ctx(topic, ns=i) for i in range(count)])
    assert item.path == f"/tb3{topic}"
    rows = _rows(item)
    assert rows["TextLog:text"] == [m.data for m in run]
    assert rows["TextLog:text"][0] == first
    assert rows["TextLog:level"] == ["INFO"] * count
    (single,) = convert(spec, run[0], _ctx(topic))
    assert _rows(single) == {"TextLog:text": [first], "TextLog:level": ["INFO"]}
