"""One converter contract, one timestamp rule: for every row of the type table, a run of messages
converted at once gives the rows its messages give converted one at a time (each a run of its
own, as a live robot's messages often come), on a run mixing stamped messages with unstamped
ones (header stamp zero): the same entity paths, component values and timelines per row, an
unstamped message's rows without ros_time, the same counts and warnings.

The paths compared are the dispatcher's, on the payloads: one ``dispatch`` of the whole run
against one ``dispatch`` per message. The table's slow converters (walls, latest-only by design)
are left out; so are the frame tree's placements and the warnings' rows, which are logged once
for what they note first (the warnings' texts and the counters are compared instead)."""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.core.contract import WARNINGS_PATH
from host_bridge.core.decode import Decoder
from host_bridge.core.schemas import base_typestore
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.registry import CATCH_ALL, Registry, Row, default_registry
from robot_relay.wire import MessageDefinition, RawMessage
from tests.host_bridge.converters.test_joints import ARM, joints_ctx
from tests.host_bridge.converters.test_laser import noisy_ranges, scan
from tests.host_bridge.converters.test_video import H264, compressed_video, encode
from tests.host_bridge.sensor_test_support import default_message
from tests.host_bridge.test_columnar_dispatch import (
    ROBOT,
    SECOND,
    RecordingSink,
    converted,
    float64,
    imu,
    joint_state,
    nav_sat_fix,
    odometry,
    pose_stamped,
    rows,
    temperature,
    tf,
    twist_stamped,
)
from tests.host_bridge.test_user_bags import CHANGE_STATE_DEFINITION, CHANGE_STATE_EVENTS

# The table without its slow converters (latest-only: how many of a run's maps get walls
# depends on timing, not on the path).
TABLE = Registry([dataclasses.replace(row, slow=None) for row in default_registry().rows()])
STORE = base_typestore()
ROS1 = get_typestore(Stores.ROS1_NOETIC)
COUNT = 6
UNSTAMPED = (1, 4)
"""The messages of each run whose header stamp is zero: no stamp."""
SERVICE_EVENT = "lifecycle_msgs/srv/ChangeState_Event"
CATCH_ALL_EXAMPLE = "sensor_msgs/msg/Joy"
"""A type with a header and no row of its own: the generic converter's."""


def stamp_of(i: int) -> int:
    return 0 if i in UNSTAMPED else 100 * SECOND + 10_000_000 * i


def log_time_of(i: int) -> int:
    return 7 * SECOND + 5_000_000 * i


def time_msg(ns: int) -> Any:
    return STORE.types["builtin_interfaces/msg/Time"](sec=ns // SECOND, nanosec=ns % SECOND)


def stamp_field(message: Any) -> tuple[Any, str] | None:
    """Where ``message`` keeps its stamp: its header, or the field its type has instead (a
    /rosout line's, a CompressedVideo's, a service event's); None for a type without one."""
    for holder, name in ((getattr(message, "header", None), "stamp"), (message, "stamp"),
                         (message, "timestamp"), (getattr(message, "info", None), "stamp")):
        if holder is not None and hasattr(holder, name):
            return holder, name
    return None


def stamp(message: Any, ns: int) -> Any:
    """``message`` stamped ``ns`` (0: no stamp), if its type has a stamp."""
    found = stamp_field(message)
    if found is not None:
        holder, name = found
        setattr(holder, name, type(getattr(holder, name))(sec=ns // SECOND, nanosec=ns % SECOND))
    return message


def jpeg(i: int) -> bytes:
    ok, encoded = cv2.imencode(".jpg", np.full((8, 12, 3), 20 * i, np.uint8))
    assert ok
    return bytes(encoded)


def compressed_image(i: int, ns: int) -> Any:
    """Stills and H.264 pictures on one topic: the still path and the video path of one run."""
    fmt, data = ("jpeg", jpeg(i)) if i % 2 else ("h264", encode(H264).packets[i])
    header = STORE.types["std_msgs/msg/Header"](stamp=time_msg(ns), frame_id="camera")
    return STORE.types["sensor_msgs/msg/CompressedImage"](header=header, format=fmt,
                                                          data=np.frombuffer(data, np.uint8))


def ros2_log(i: int, ns: int) -> Any:
    return STORE.types["rcl_interfaces/msg/Log"](
        stamp=time_msg(ns), level=10 * (i % 5 + 1), name="talker", msg=f"line {i}",
        file="talker.cpp", function="main", line=i)


def ros1_log(i: int, ns: int) -> Any:
    header = ROS1.types["std_msgs/msg/Header"](
        seq=i, stamp=ROS1.types["builtin_interfaces/msg/Time"](sec=ns // SECOND, nanosec=ns % SECOND),
        frame_id="")
    return ROS1.types["rosgraph_msgs/msg/Log"](
        header=header, level=1 << (i % 5), name="/talker", msg=f"line {i}", file="talker.py",
        function="main", line=i, topics=["/chatter"])


def multi_array(msgtype: str) -> Callable[[int, int], Any]:
    def build(i: int, _ns: int) -> Any:
        message = default_message(STORE, msgtype)
        message.data = np.arange(2 + i % 3, dtype=message.data.dtype)  # lengths vary in the run
        return message

    return build


def battery(i: int, ns: int) -> Any:
    message = stamp(default_message(STORE, "sensor_msgs/msg/BatteryState"), ns)
    message.voltage, message.percentage = 12.0 - 0.1 * i, 0.9 - 0.01 * i
    message.cell_voltage = np.full(3 if i % 2 else 4, 4.0 - 0.01 * i, np.float32)
    return message


def joy(i: int, ns: int) -> Any:
    message = stamp(default_message(STORE, CATCH_ALL_EXAMPLE), ns)
    message.axes = np.linspace(-1.0, 1.0, 80 if i == 3 else 4, dtype=np.float32)  # one bar chart
    message.buttons = np.array([i % 2, 1], np.int32)
    return message


# The types whose run and message paths differ in code (read as columns, or decoded and batched
# into columns) get messages with content; the others (converted one message at a time, alike in
# both paths) their default message, stamped.
BUILDERS: dict[str, Callable[[int, int], Any]] = {
    "tf2_msgs/msg/TFMessage": tf,
    "sensor_msgs/msg/Imu": imu,
    "sensor_msgs/msg/JointState": joint_state,
    "sensor_msgs/msg/NavSatFix": nav_sat_fix,
    "nav_msgs/msg/Odometry": odometry,
    "geometry_msgs/msg/PoseStamped": pose_stamped,
    "geometry_msgs/msg/TwistStamped": twist_stamped,
    "sensor_msgs/msg/Temperature": temperature,
    "std_msgs/msg/Float64": float64,
    "sensor_msgs/msg/LaserScan": lambda i, ns: scan(noisy_ranges(360, seed=i), increment=np.pi / 180,
                                                    stamp_ns=ns),
    "sensor_msgs/msg/CompressedImage": compressed_image,
    "foxglove_msgs/msg/CompressedVideo": lambda i, ns: compressed_video("h264", encode(H264).packets[i], ns),
    "rcl_interfaces/msg/Log": ros2_log,
    "rosgraph_msgs/msg/Log": ros1_log,
    "std_msgs/msg/String": lambda i, _: STORE.types["std_msgs/msg/String"](data=f"line {i}"),
    "sensor_msgs/msg/BatteryState": battery,
    "std_msgs/msg/Float32MultiArray": multi_array("std_msgs/msg/Float32MultiArray"),
    "std_msgs/msg/Int16MultiArray": multi_array("std_msgs/msg/Int16MultiArray"),
    CATCH_ALL_EXAMPLE: joy,
}


def service_events() -> tuple[Typestore, MessageDefinition, list[Any]]:
    """A request and its response (rclpy's bytes, test_user_bags), in turn."""
    definition = MessageDefinition("ros2msg", CHANGE_STATE_DEFINITION)
    store = Decoder().typestore_for(SERVICE_EVENT, definition)
    return store, definition, [
        store.deserialize_cdr(bytes.fromhex(CHANGE_STATE_EVENTS[i % 2]), SERVICE_EVENT) for i in range(COUNT)
    ]


Example = tuple[str, str, Typestore, MessageDefinition | None, list[Any]]


def example(row: Row) -> Example:
    """A type of ``row`` (one of a family's), its topic, typestore and definition (None: the
    bundled one), and the messages of a run of it, stamped but for ``UNSTAMPED``."""
    msgtype = {CATCH_ALL: CATCH_ALL_EXAMPLE, "*/srv/*_Event": SERVICE_EVENT}.get(row.msgtype, row.msgtype)
    topic = "/tf" if msgtype == "tf2_msgs/msg/TFMessage" else "/" + msgtype.rsplit("/", 1)[-1].lower()
    if msgtype == SERVICE_EVENT:
        store, definition, events = service_events()
        return msgtype, topic, store, definition, [stamp(e, stamp_of(i)) for i, e in enumerate(events)]
    if row.topics is not None:  # std_msgs/String on /robot_description: a robot model
        model = STORE.types["std_msgs/msg/String"](data=ARM)
        return msgtype, "/robot_description", STORE, None, [model] * COUNT
    if msgtype in BUILDERS:
        messages = [BUILDERS[msgtype](i, stamp_of(i)) for i in range(COUNT)]
    else:
        messages = [stamp(default_message(STORE, msgtype), stamp_of(i)) for i in range(COUNT)]
    if msgtype not in STORE.types:  # a ROS 1 bag's type, as the relay sends it
        text = ROS1.generate_msgdef(msgtype, ros_version=2)[0]
        return msgtype, topic, ROS1, MessageDefinition("ros2msg", text), messages
    return msgtype, topic, STORE, None, messages


def raw_run(found: Example) -> list[RawMessage]:
    msgtype, topic, store, definition, messages = found
    return [RawMessage(ROBOT, topic, msgtype, bytes(store.serialize_cdr(m, msgtype)), definition,
                       log_ns=log_time_of(i)) for i, m in enumerate(messages)]


def dispatcher(sink: RecordingSink) -> Dispatcher:
    found = Dispatcher(sink, registry=TABLE, strict=False)
    found.robot_state(ROBOT).model = joints_ctx(ROBOT, ARM).robot_state.model
    return found


def warnings(sink: RecordingSink) -> set[str]:
    return {
        text
        for item in sink.entries() if item.path == WARNINGS_PATH
        for archetype in getattr(item, "archetypes", ())
        for text in archetype.text.as_arrow_array().to_pylist()
    }


def ros_times_by_log_time(found: Counter[Any]) -> dict[int, set[bool]]:
    """Per message (its log time), whether its rows have a ros_time; static rows left out."""
    by_message: dict[int, set[bool]] = {}
    for _, times, _, _ in found:
        timelines = {} if times == ("static",) else dict(times)
        if "log_time" in timelines:
            by_message.setdefault(timelines["log_time"], set()).add("ros_time" in timelines)
    return by_message


@pytest.mark.parametrize("row", TABLE.rows(),
                         ids=lambda row: row.msgtype + (" (by topic)" if row.topics else ""))
def test_a_run_gives_the_rows_its_messages_give_one_by_one(row: Row) -> None:
    found = example(row)
    run = raw_run(found)
    whole_sink, one_by_one_sink = RecordingSink(), RecordingSink()
    whole, one_by_one = dispatcher(whole_sink), dispatcher(one_by_one_sink)
    whole.dispatch(run)
    for raw in run:
        one_by_one.dispatch([raw])

    logged = rows(converted(whole_sink))
    assert logged == rows(converted(one_by_one_sink))
    topic = run[0].topic
    counts = [(c.received, c.converted, c.dropped) for c in
              (d.counters[(ROBOT, topic)] for d in (whole, one_by_one))]
    assert counts[0] == counts[1]
    assert counts[0][0] == COUNT
    assert sum(counts[0][1:]) == COUNT
    assert warnings(whole_sink) == warnings(one_by_one_sink)
    if stamp_field(found[4][0]) is not None:
        # A message's rows have a ros_time (its stamp) unless it is unstamped; never ros_time 0.
        by_message = ros_times_by_log_time(logged)
        for i in range(COUNT):
            assert by_message.get(log_time_of(i), {i not in UNSTAMPED}) == {i not in UNSTAMPED}, i
    assert not [times for _, times, _, _ in logged if ("ros_time", 0) in times]


@pytest.mark.parametrize("msgtype", sorted(BUILDERS))
def test_the_examples_with_content_convert_every_message(msgtype: str) -> None:
    """The rows whose paths differ in code log rows for every message of the run above (two
    empty outputs compared would prove nothing)."""
    run = raw_run(example(TABLE.row(msgtype, "/topic")))
    sink = RecordingSink()
    found = dispatcher(sink)
    found.dispatch(run)
    counters = found.counters[(ROBOT, run[0].topic)]
    assert (counters.converted, counters.dropped) == (COUNT, 0)
    logged = {dict(times).get("log_time") for _, times, _, _ in rows(converted(sink))
              if times != ("static",)}
    no_fix = {log_time_of(3)} if msgtype == "sensor_msgs/msg/NavSatFix" else set()  # nothing to show
    assert {raw.log_ns for raw in run} - no_fix <= logged


def test_every_row_of_the_table_has_an_example() -> None:
    assert [row.msgtype for row in TABLE.rows() if row.is_family] == ["*/srv/*_Event", CATCH_ALL]
    assert CATCH_ALL_EXAMPLE not in default_registry().types()
    assert all(len(raw_run(example(row))) == COUNT for row in TABLE.rows())
