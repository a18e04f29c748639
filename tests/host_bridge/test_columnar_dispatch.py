"""The dispatcher's columnar path (issue 13): a run of payloads read as columns and converted with
no per-message decode gives the same rows (entity paths, timelines, component values, frames) as
the message path (rosbags decodes each payload, the converter takes it as a run of its own) on the
same payloads; a bad payload costs only itself; restamp, zero stamps and strings changing within
a run (blocks) keep their rows and times exact."""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from host_bridge.core.columns import PackedPayloads
from host_bridge.core.contract import ColumnsItem, ConvertContext, LogEntry, message_run
from host_bridge.core.decode import Decoder
from host_bridge.core.frames import frames_logged
from host_bridge.core.state import RobotState, TopicState
from host_bridge.errors import PartialConvertError
from host_bridge.inputs.base import MessageRun
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.config import HostConfig
from host_bridge.table.registry import default_registry
from robot_relay.wire import RawMessage
from tests.host_bridge.converters.test_joints import ARM, joints_ctx

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
ROBOT = "tb3"
REGISTRY = default_registry()
SECOND = 1_000_000_000
IMU = "sensor_msgs/msg/Imu"
TF = "tf2_msgs/msg/TFMessage"
JOINT_STATE = "sensor_msgs/msg/JointState"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"

Row = tuple[str, tuple[Any, ...], str, str]


class RecordingSink:
    """What the dispatcher logs, call by call."""

    def __init__(self) -> None:
        self.calls: list[tuple[list[LogEntry], dict[str, int]]] = []

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        self.calls.append((list(entries), dict(times)))

    def close(self) -> None:
        pass

    def entries(self) -> list[LogEntry]:
        return [entry for entries, _ in self.calls for entry in entries]


def rows(calls: Sequence[tuple[Sequence[LogEntry], Mapping[str, int]]]) -> Counter[Row]:
    """Every logged row as (entity path, its times, component, values), columns and single
    archetypes alike, so a run's columns compare with messages logged one by one."""
    found: Counter[Row] = Counter()
    for entries, call_times in calls:
        for entry in entries:
            if isinstance(entry, ColumnsItem):
                columns = {
                    column.component_descriptor().component: column.as_arrow_array().to_pylist()
                    for column in entry.columns
                }
                count = len(next(iter(columns.values())))
                for name, values in entry.times.items():
                    assert len(values) == count, (entry.path, name)
                for i in range(count):
                    times = tuple(sorted((name, int(v[i])) for name, v in entry.times.items()))
                    for component, values in columns.items():
                        found[(entry.path, times, component, repr(values[i]))] += 1
                continue
            when: tuple[Any, ...] = ("static",) if entry.static else tuple(
                sorted((entry.times if entry.times is not None else call_times).items())
            )
            for archetype in entry.archetypes:
                for batch in archetype.as_component_batches():
                    values = batch.as_arrow_array().to_pylist()
                    found[(entry.path, when, batch.component_descriptor().component, repr(values))] += 1
    return found


def stamp(ns: int) -> Any:
    return T["builtin_interfaces/msg/Time"](sec=ns // SECOND, nanosec=ns % SECOND)


def header(ns: int, frame_id: str) -> Any:
    return T["std_msgs/msg/Header"](stamp=stamp(ns), frame_id=frame_id)


def vector3(x: float, y: float, z: float) -> Any:
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def imu(i: int, ns: int, frame_id: str = "imu_link") -> Any:
    angle = 0.01 * i
    return T[IMU](
        header=header(ns, frame_id),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(angle), w=np.cos(angle)),
        orientation_covariance=np.full(9, 0.01 * i),
        angular_velocity=vector3(0.1 * i, -0.2, 0.3),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector3(0.5, 0.25 * i, 9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


def tf(i: int, ns: int, child: str = "base_link") -> Any:
    def transform(parent: str, child: str, x: float, stamp_ns: int) -> Any:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp_ns, parent),
            child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=vector3(x, 2.0 * x, 0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(x), w=np.cos(x)),
            ),
        )

    # The second transform is stamped 1 ms later: each row keeps its own stamp.
    return T[TF](transforms=[transform("map", "odom", 0.001 * i, ns),
                             transform("odom", child, 0.1 * i, ns + 1_000_000)])


def joint_state(i: int, ns: int, names: Sequence[str] = ("shoulder", "lift")) -> Any:
    values = np.array([0.1 * i + k for k in range(len(names))])
    return T[JOINT_STATE](
        header=header(ns, ""), name=list(names), position=values, velocity=-values,
        effort=np.array([]),
    )


def nav_sat_fix(i: int, ns: int) -> Any:
    return T[NAV_SAT_FIX](
        header=header(ns, "gps"),
        status=T["sensor_msgs/msg/NavSatStatus"](status=-1 if i == 3 else 0, service=1),
        latitude=48.85 + 1e-5 * i, longitude=2.35 - 1e-5 * i, altitude=35.0 + i,
        position_covariance=np.arange(9, dtype=np.float64), position_covariance_type=2 if i % 2 else 0,
    )


def pose(i: int) -> Any:
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=0.05 * i, y=1.0, z=0.0),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0 if i == 2 else 1.0),
    )


def odometry(i: int, ns: int) -> Any:
    return T["nav_msgs/msg/Odometry"](
        header=header(ns, "odom"), child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose(i), covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=vector3(0.2 * i, 0.0, 0.0),
                                               angular=vector3(0.0, 0.0, -0.1)),
            covariance=np.zeros(36)),
    )


def pose_stamped(i: int, ns: int) -> Any:
    return T["geometry_msgs/msg/PoseStamped"](header=header(ns, "map" if i % 5 else ""), pose=pose(i))


def twist_stamped(i: int, ns: int) -> Any:
    return T["geometry_msgs/msg/TwistStamped"](
        header=header(ns, "base_link"),
        twist=T["geometry_msgs/msg/Twist"](linear=vector3(0.1 * i, 0.0, 0.0), angular=vector3(0.0, 0.0, 1.0)),
    )


def temperature(i: int, ns: int) -> Any:
    return T["sensor_msgs/msg/Temperature"](header=header(ns, "cpu"), temperature=40.0 + i, variance=0.0)


def float64(i: int, _ns: int) -> Any:
    return T["std_msgs/msg/Float64"](data=0.5 * i)


def payloads(msgtype: str, messages: Sequence[Any]) -> list[bytes]:
    return [bytes(STORE.serialize_cdr(message, msgtype)) for message in messages]


def raws(topic: str, msgtype: str, data: Sequence[bytes], *, live: bool = False) -> list[RawMessage]:
    """One RawMessage per payload, 5 ms apart: a bag's log time, or a relay's receive time."""
    arrivals = [7 * SECOND + 5_000_000 * i for i in range(len(data))]
    if live:
        return [RawMessage(ROBOT, topic, msgtype, d, receive_ns=t)
                for d, t in zip(data, arrivals, strict=True)]
    return [RawMessage(ROBOT, topic, msgtype, d, log_ns=t) for d, t in zip(data, arrivals, strict=True)]


def config(tmp_path: Path, text: str) -> HostConfig:
    path = tmp_path / "host.yaml"
    path.write_text(text)
    return HostConfig.load(path, REGISTRY)


def dispatcher(sink: RecordingSink, host_config: HostConfig | None = None,
               model_xml: str | None = None) -> Dispatcher:
    found = Dispatcher(sink, registry=REGISTRY, config=host_config, strict=False)
    if model_xml is not None:
        found.robot_state(ROBOT).model = joints_ctx(ROBOT, model_xml).robot_state.model
    return found


def message_path(run: Sequence[RawMessage], *, restamp: bool = False,
                 model_xml: str | None = None) -> list[tuple[list[LogEntry], dict[str, int]]]:
    """The reference: rosbags decodes each payload, and the type's converter takes it as a run
    of its own, with its arrival times."""
    decoder = Decoder()
    robot_state = RobotState()
    if model_xml is not None:
        robot_state.model = joints_ctx(ROBOT, model_xml).robot_state.model
    topic_state = TopicState()
    converter = REGISTRY.get(run[0].msgtype, run[0].topic)
    calls = []
    for raw in run:
        arrivals = {name: ns for name, ns in (("receive_time", raw.receive_ns), ("log_time", raw.log_ns))
                    if ns is not None}
        ctx = ConvertContext(robot=ROBOT, topic=raw.topic, entity_path=f"/{ROBOT}{raw.topic}",
                             times=arrivals, topic_state=topic_state, robot_state=robot_state,
                             restamp=restamp)
        one = message_run([decoder.decode(raw)], [ctx])
        try:
            calls.append((converter(one), one.row_times()))
        except PartialConvertError as err:  # JointState without a model: its plots only
            calls.append((err.items, one.row_times()))
    return calls


def converted(sink: RecordingSink) -> list[tuple[list[LogEntry], dict[str, int]]]:
    """What the converters logged: the frames' placements, view target and warnings left out."""
    return [(entries, times) for entries, times in sink.calls
            if not any(e.path.startswith((f"/{ROBOT}/tf_static/", "/_swanky/")) or e.path == f"/{ROBOT}"
                       for e in entries)]


def assert_same_rows(run: list[RawMessage], **kwargs: Any) -> tuple[Counter[Row], Dispatcher]:
    sink = RecordingSink()
    robot_dispatcher = dispatcher(sink, kwargs.pop("host_config", None), kwargs.get("model_xml"))
    # The columnar path must be the one taken: no message of the run is decoded.
    robot_dispatcher.decoder.decode = _no_decode  # type: ignore[method-assign]
    robot_dispatcher.dispatch(run)
    got = rows(converted(sink))
    expected = rows(message_path(run, **kwargs))
    assert got == expected
    counters = robot_dispatcher.counters[(ROBOT, run[0].topic)]
    assert (counters.received, counters.converted, counters.dropped) == (len(run), len(run), 0)
    return got, robot_dispatcher


def _no_decode(raw: RawMessage) -> Any:
    raise AssertionError(f"{raw.topic}: decoded message by message")


def values_at(found: Counter[Row], path: str, component: str) -> list[tuple[tuple[Any, ...], str]]:
    return sorted((times, values) for (p, times, c, values) in found if p == path and c == component)


CASES: dict[str, tuple[str, str, Callable[[int, int], Any]]] = {
    "imu": ("/imu", IMU, imu),
    "tf": ("/tf", TF, tf),
    "joint_state": ("/joint_states", JOINT_STATE, joint_state),
    "nav_sat_fix": ("/gps/fix", NAV_SAT_FIX, nav_sat_fix),
    "odometry": ("/odom", "nav_msgs/msg/Odometry", odometry),
    "pose_stamped": ("/goal", "geometry_msgs/msg/PoseStamped", pose_stamped),
    "twist_stamped": ("/cmd_vel", "geometry_msgs/msg/TwistStamped", twist_stamped),
    "temperature": ("/cpu_temp", "sensor_msgs/msg/Temperature", temperature),
    "float64": ("/battery_runtime", "std_msgs/msg/Float64", float64),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_run_in_columns_gives_the_rows_of_the_message_path(case: str) -> None:
    topic, msgtype, make = CASES[case]
    messages = [make(i, 100 * SECOND + 10_000_000 * i) for i in range(40)]
    found, _ = assert_same_rows(raws(topic, msgtype, payloads(msgtype, messages)))
    assert found  # and something was logged at all: the exact values follow per type below


def test_imu_rows_hold_the_header_stamps_and_values() -> None:
    messages = [imu(i, 100 * SECOND + 5_000_000 * i) for i in range(20)]
    found, _ = assert_same_rows(raws("/imu", IMU, payloads(IMU, messages)))
    rates = values_at(found, "/tb3/imu/angular_velocity", "Scalars:scalars")
    assert len(rates) == 20
    times, values = rates[3]
    assert dict(times) == {"ros_time": 100 * SECOND + 15_000_000, "log_time": 7 * SECOND + 15_000_000}
    assert values == repr([0.1 * 3, -0.2, 0.3])
    parents = values_at(found, "/tb3/imu/orientation", "Transform3D:parent_frame")
    assert {v for _, v in parents} == {repr(["tb3/imu_link"])}


def test_tf_rows_are_one_per_transform_at_its_own_stamp_and_frames_are_seen() -> None:
    messages = [tf(i, 100 * SECOND + 10_000_000 * i) for i in range(10)]
    found, robot_dispatcher = assert_same_rows(raws("/tf", TF, payloads(TF, messages)))
    children = values_at(found, "/tb3/tf", "Transform3D:child_frame")
    assert len(children) == 20
    assert children[:2] == [
        ((("log_time", 7 * SECOND), ("ros_time", 100 * SECOND)), repr(["tb3/odom"])),
        ((("log_time", 7 * SECOND), ("ros_time", 100 * SECOND + 1_000_000)), repr(["tb3/base_link"])),
    ]
    translations = values_at(found, "/tb3/tf", "Transform3D:translation")
    np.testing.assert_allclose(eval(translations[-1][1]), [[0.1 * 9, 0.2 * 9, 0.0]], rtol=1e-6)
    # The frame tree saw the relations: map is the 3D view's target, TF children are known.
    assert robot_dispatcher.frames(ROBOT).target == "tb3/map"
    assert robot_dispatcher.robot_state(ROBOT).tf_children == {"odom", "base_link"}


def test_a_tf_frame_changing_mid_run_keeps_each_message_with_its_frames() -> None:
    messages = [tf(i, 100 * SECOND + i, "base_link" if i < 4 else "base_footprint") for i in range(8)]
    # Frames of different lengths: two layouts, read in one call.
    found, robot_dispatcher = assert_same_rows(raws("/tf", TF, payloads(TF, messages)))
    children = [v for _, v in values_at(found, "/tb3/tf", "Transform3D:child_frame")]
    assert Counter(children) == {repr(["tb3/odom"]): 8, repr(["tb3/base_link"]): 4,
                                 repr(["tb3/base_footprint"]): 4}
    assert robot_dispatcher.frames(ROBOT).unplaced() == []  # every frame has its TF parent
    relations, _ = frames_logged(
        [e for entries, _ in message_path(raws("/tf", TF, payloads(TF, messages))) for e in entries]
    )
    assert ("tb3/base_footprint", "tb3/odom") in relations


def test_tf_messages_of_one_and_of_two_transforms_in_one_run() -> None:
    # robot_state_publisher's wheels: a message per wheel and one with both, in one run; the
    # run's blocks differ in width, each is read on its own.
    messages = [tf(i, 100 * SECOND + 10_000_000 * i) for i in range(6)]
    for i in (1, 4):
        messages[i].transforms = messages[i].transforms[1:]
    found, _ = assert_same_rows(raws("/tf", TF, payloads(TF, messages)))
    children = values_at(found, "/tb3/tf", "Transform3D:child_frame")
    assert Counter(v for _, v in children) == {repr(["tb3/odom"]): 4, repr(["tb3/base_link"]): 6}
    translations = [v for _, v in values_at(found, "/tb3/tf", "Transform3D:translation")]
    np.testing.assert_allclose(eval(translations[-1]), [[0.5, 1.0, 0.0]], rtol=1e-6)


def test_imu_frame_changing_mid_run_gives_a_block_per_frame() -> None:
    messages = [imu(i, 100 * SECOND + i, "imu_a" if i % 3 else "imu_b") for i in range(12)]
    found, _ = assert_same_rows(raws("/imu", IMU, payloads(IMU, messages)))
    parents = Counter(v for _, v in values_at(found, "/tb3/imu/orientation", "Transform3D:parent_frame"))
    assert parents == {repr(["tb3/imu_a"]): 8, repr(["tb3/imu_b"]): 4}


def test_joint_names_changing_mid_run_and_the_robot_model_moving() -> None:
    messages = [joint_state(i, 100 * SECOND + i, ("shoulder", "lift") if i % 2 else ("lift",))
                for i in range(6)]
    found, _ = assert_same_rows(raws("/joint_states", JOINT_STATE, payloads(JOINT_STATE, messages)),
                                model_xml=ARM)
    lift = values_at(found, "/tb3/joint_states/lift/position", "Scalars:scalars")
    assert [v for _, v in lift] == [repr([0.1 * i + (1 if i % 2 else 0)]) for i in range(6)]
    shoulder = values_at(found, "/tb3/robot_model/joints/shoulder", "Transform3D:parent_frame")
    assert [dict(t)["ros_time"] for t, _ in shoulder] == [100 * SECOND + i for i in (1, 3, 5)]
    # grip mimics shoulder: it moves exactly when shoulder does.
    grip = values_at(found, "/tb3/robot_model/joints/grip", "Transform3D:quaternion")
    assert [dict(t)["ros_time"] for t, _ in grip] == [100 * SECOND + i for i in (1, 3, 5)]


def test_joint_states_without_a_model_convert_their_plots_and_warn_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    sink = RecordingSink()
    robot_dispatcher = dispatcher(sink)
    messages = [joint_state(i, 100 * SECOND + i) for i in range(50)]
    run = raws("/joint_states", JOINT_STATE, payloads(JOINT_STATE, messages))
    with caplog.at_level(logging.WARNING, logger="swanky.host"):
        robot_dispatcher.dispatch(run[:25])
        robot_dispatcher.dispatch(run[25:])
    counters = robot_dispatcher.counters[(ROBOT, "/joint_states")]
    assert (counters.converted, counters.dropped, counters.warnings) == (50, 0, 2)
    assert len([r for r in caplog.records if "no robot model" in r.getMessage()]) == 1
    found = rows(sink.calls)
    assert len(values_at(found, "/tb3/joint_states/shoulder/velocity", "Scalars:scalars")) == 50


def test_nav_sat_fix_skips_no_fix_and_sizes_by_covariance() -> None:
    messages = [nav_sat_fix(i, 100 * SECOND + i) for i in range(6)]
    found, _ = assert_same_rows(raws("/gps/fix", NAV_SAT_FIX, payloads(NAV_SAT_FIX, messages)))
    positions = values_at(found, "/tb3/gps/fix", "GeoPoints:positions")
    assert [dict(t)["ros_time"] for t, _ in positions] == [100 * SECOND + i for i in (0, 1, 2, 4, 5)]
    radii = [v for _, v in values_at(found, "/tb3/gps/fix", "GeoPoints:radii")]
    assert radii[1] == repr([2.0])  # covariance known (odd i): sqrt(max(var east 0, var north 4))


def test_a_truncated_payload_costs_only_itself_and_is_warned_once_naming_the_topic(
    caplog: pytest.LogCaptureFixture,
) -> None:
    messages = [imu(i, 100 * SECOND + i) for i in range(30)]
    data = payloads(IMU, messages)
    good = raws("/imu", IMU, data)
    bad = list(good)
    bad[7] = RawMessage(ROBOT, "/imu", IMU, data[7][:40], log_ns=good[7].log_ns)
    bad[20] = RawMessage(ROBOT, "/imu", IMU, data[20][:-30], log_ns=good[20].log_ns)
    sink = RecordingSink()
    robot_dispatcher = dispatcher(sink)
    with caplog.at_level(logging.WARNING, logger="swanky.host"):
        robot_dispatcher.dispatch(bad)
    counters = robot_dispatcher.counters[(ROBOT, "/imu")]
    assert (counters.received, counters.converted, counters.dropped, counters.warnings) == (30, 28, 2, 2)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1
    assert warnings[0].startswith("[tb3] /imu: ")
    assert "payload does not deserialize" in warnings[0]
    kept = [raw for i, raw in enumerate(good) if i not in (7, 20)]
    assert rows(converted(sink)) == rows(message_path(kept))


def test_a_truncated_payload_in_a_packed_bag_run_costs_only_itself(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A bag's run (payloads in one buffer, record headers between them) with a payload cut
    short in the middle: that message is dropped and warned about, the others convert."""
    data = payloads(IMU, [imu(i, 100 * SECOND + i) for i in range(30)])
    data[11] = data[11][:-30]
    buffer, starts = b"", []
    for payload in data:
        buffer += b"\x05" + bytes(30)  # a Message record's header
        starts.append(len(buffer))
        buffer += payload
    ends = [start + len(payload) for start, payload in zip(starts, data, strict=True)]
    packed = PackedPayloads((buffer,), np.zeros(30, np.intp), np.array(starts), np.array(ends))
    log_ns = np.array([7 * SECOND + 5_000_000 * i for i in range(30)], np.int64)
    run = MessageRun(ROBOT, "/imu", IMU, None, packed, log_ns)
    sink = RecordingSink()
    robot_dispatcher = dispatcher(sink)
    with caplog.at_level(logging.WARNING, logger="swanky.host"):
        robot_dispatcher.dispatch(run)
    counters = robot_dispatcher.counters[(ROBOT, "/imu")]
    assert (counters.received, counters.converted, counters.dropped, counters.warnings) == (30, 29, 1, 1)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1
    assert warnings[0].startswith("[tb3] /imu: ")
    assert "payload does not deserialize" in warnings[0]
    kept = [raw for i, raw in enumerate(raws("/imu", IMU, data)) if i != 11]
    assert rows(converted(sink)) == rows(message_path(kept))


def test_restamp_puts_the_arrival_time_on_ros_time(tmp_path: Path) -> None:
    messages = [imu(i, 100 * SECOND + i) for i in range(10)]
    run = raws("/imu", IMU, payloads(IMU, messages), live=True)
    found, _ = assert_same_rows(run, restamp=True,
                                host_config=config(tmp_path, "topics:\n  /imu:\n    restamp: true\n"))
    times = [dict(t) for t, _ in values_at(found, "/tb3/imu/linear_acceleration", "Scalars:scalars")]
    assert times == [{"ros_time": raw.receive_ns, "receive_time": raw.receive_ns} for raw in run]


def test_zero_stamps_have_no_ros_time_and_the_others_keep_theirs() -> None:
    messages = [imu(i, 0 if i in (2, 5) else 100 * SECOND + i) for i in range(8)]
    tfs = [tf(i, 0 if i == 1 else 100 * SECOND + i) for i in range(4)]
    found, _ = assert_same_rows(raws("/imu", IMU, payloads(IMU, messages)))
    times = [dict(t) for t, _ in values_at(found, "/tb3/imu/angular_velocity", "Scalars:scalars")]
    assert sum("ros_time" not in t for t in times) == 2
    assert sorted(t["log_time"] for t in times if "ros_time" not in t) == [
        7 * SECOND + 5_000_000 * i for i in (2, 5)
    ]
    found, _ = assert_same_rows(raws("/tf", TF, payloads(TF, tfs)))
    stamps = [dict(t).get("ros_time") for t, _ in values_at(found, "/tb3/tf", "Transform3D:child_frame")]
    stamped = sorted(s for i in (0, 2, 3) for s in (100 * SECOND + i, 100 * SECOND + i + 1_000_000))
    assert sorted(stamps, key=lambda s: s or 0) == [None, 1_000_000, *stamped]
