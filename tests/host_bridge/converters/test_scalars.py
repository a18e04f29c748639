"""Small numeric messages -> Scalars, per message and as send_columns runs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from host_bridge.converters import scalars
from host_bridge.core.contract import ColumnsItem, ConvertContext, Converter, LogEntry, PerMessage
from host_bridge.core.schemas import base_typestore
from host_bridge.errors import ConvertError
from host_bridge.table.registry import default_registry, loaded
from tests.host_bridge.sensor_test_support import (
    column_rows,
    columns_item,
    default_message,
    header,
    make_ctx,
    msg,
    read_topic,
    reads_columns_only,
)
from tests.host_bridge.sensor_test_support import convert as convert_one
from tests.host_bridge.sensor_test_support import convert_run as convert_messages

REGISTRY = default_registry()


def converter_of(msgtype: str) -> Converter:
    """The type's row in the table; JointState's plots only (its row also moves the model)."""
    if msgtype == "sensor_msgs/msg/JointState":
        return scalars.JOINT_STATE
    return REGISTRY.get(msgtype)


def convert(msgtype: str, message: Any, ctx: ConvertContext) -> list[LogEntry]:
    return convert_one(converter_of(msgtype), message, ctx)


def convert_run(msgtype: str, msgs: list[Any], ctxs: list[ConvertContext]) -> list[LogEntry]:
    return convert_messages(converter_of(msgtype), msgs, ctxs)


@pytest.mark.parametrize(
    ("name", "value", "expected"),
    [
        ("Bool", True, 1.0),
        ("Byte", -56, -56.0),  # rosbags reads a CDR byte as int8
        ("Char", 65, 65.0),
        ("Int8", -5, -5.0),
        ("UInt8", 255, 255.0),
        ("Int16", -32768, -32768.0),
        ("UInt16", 65535, 65535.0),
        ("Int32", -7, -7.0),
        ("UInt32", 4_000_000_000, 4e9),
        ("Int64", -(2**40), -(2.0**40)),
        ("UInt64", 2**53, 2.0**53),
        ("Float32", 1.5, 1.5),
        ("Float64", -0.125, -0.125),
    ],
)
def test_std_numbers(name: str, value: Any, expected: float) -> None:
    msgtype = f"std_msgs/msg/{name}"
    (item,) = convert(msgtype, msg(msgtype, data=value), make_ctx("/n"))
    assert isinstance(item, ColumnsItem)
    assert item.path == "/r/n"
    np.testing.assert_array_equal(np.concatenate(column_rows(item, "Scalars:scalars")), [expected])


def test_timer_named_float32_is_a_plain_time_series() -> None:
    msgs = [msg("std_msgs/msg/Float32", data=v) for v in (0.5, 0.25, 2.0)]
    # No header: the arrival times are the message's times.
    ctxs = [make_ctx("/instrumentation/timer/foo", times={"log_time": t}) for t in (10, 20, 30)]
    (item,) = convert_run("std_msgs/msg/Float32", msgs, ctxs)
    column = columns_item([item], "/r/instrumentation/timer/foo")
    np.testing.assert_array_equal(
        np.concatenate(column_rows(column, "Scalars:scalars")), [0.5, 0.25, 2.0]
    )
    assert list(column.times) == ["log_time"]
    np.testing.assert_array_equal(column.times["log_time"], [10, 20, 30])


def test_multiarray_is_multi_series_and_runs_allow_varying_length() -> None:
    layout = msg("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
    msgtype = "std_msgs/msg/Int16MultiArray"
    msgs = [
        msg(msgtype, layout=layout, data=np.array(values, dtype=np.int16))
        for values in ([1, -2, 3], [4, 5, 6], [7, 8])
    ]
    (item,) = convert(msgtype, msgs[0], make_ctx("/arr"))
    assert isinstance(item, ColumnsItem)
    assert [r.tolist() for r in column_rows(item, "Scalars:scalars")] == [[1.0, -2.0, 3.0]]
    ctxs = [make_ctx("/arr", stamp_ns=t) for t in (1, 2, 3)]
    rows = column_rows(columns_item(convert_run(msgtype, msgs, ctxs), "/r/arr"), "Scalars:scalars")
    assert [r.tolist() for r in rows] == [[1.0, -2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0]]


def test_time_and_duration_as_seconds() -> None:
    for msgtype in ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"):
        (item,) = convert(msgtype, msg(msgtype, sec=12, nanosec=500_000_000), make_ctx("/t"))
        assert isinstance(item, ColumnsItem)
        np.testing.assert_array_equal(np.concatenate(column_rows(item, "Scalars:scalars")), [12.5])


@pytest.mark.parametrize(
    ("name", "field"),
    [
        ("Temperature", "temperature"),
        ("FluidPressure", "fluid_pressure"),
        ("Illuminance", "illuminance"),
        ("RelativeHumidity", "relative_humidity"),
    ],
)
def test_environment_sensors(name: str, field: str) -> None:
    msgtype = f"sensor_msgs/msg/{name}"
    message = msg(msgtype, header=header("env", 5_000_000_007), variance=0.0, **{field: 21.75})
    (item,) = convert(msgtype, message, make_ctx("/env"))
    assert isinstance(item, ColumnsItem)
    assert item.path == "/r/env"
    np.testing.assert_array_equal(np.concatenate(column_rows(item, "Scalars:scalars")), [21.75])
    assert item.times == {"ros_time": [5_000_000_007]}


def battery(voltage: float, cells: list[float]) -> Any:
    return msg(
        "sensor_msgs/msg/BatteryState",
        header=header(),
        voltage=voltage,
        temperature=31.0,
        current=-1.5,
        charge=2.25,
        capacity=4.0,
        design_capacity=5.0,
        percentage=0.5,
        power_supply_status=2,
        power_supply_health=1,
        power_supply_technology=3,
        present=True,
        cell_voltage=np.array(cells, dtype=np.float32),
        cell_temperature=np.array([], np.float32),
        location="",
        serial_number="",
    )


def test_battery_state_scalars_and_cells() -> None:
    entries = convert(
        "sensor_msgs/msg/BatteryState", battery(12.5, [4.0, 4.25, 4.25]), make_ctx("/battery")
    )
    values = {
        name: column_rows(columns_item(entries, f"/r/battery/{name}"), "Scalars:scalars")[0].tolist()
        for name in ("voltage", "current", "charge", "percentage", "temperature", "cell_voltage")
    }
    assert values == {
        "voltage": [12.5],
        "current": [-1.5],
        "charge": [2.25],
        "percentage": [0.5],
        "temperature": [31.0],
        "cell_voltage": [4.0, 4.25, 4.25],
    }
    assert not [e for e in entries if e.path == "/r/battery/cell_temperature"]  # empty: skipped


def test_real_battery_and_float32_runs(shared_data: Path) -> None:
    bag = shared_data / "tb3_nav_sim_paths_amr" / "rosbag_demo.bag"
    msgs = list(read_topic(bag, "/battery"))
    assert len(msgs) == 111
    ctxs = [make_ctx("/battery", stamp_ns=i) for i in range(len(msgs))]
    entries = convert_run("sensor_msgs/msg/BatteryState", msgs, ctxs)
    percentage = columns_item(entries, "/r/battery/percentage")
    np.testing.assert_allclose(
        np.concatenate(column_rows(percentage, "Scalars:scalars")), [m.percentage for m in msgs]
    )
    assert msgs[0].percentage == 88.0
    runtime = list(read_topic(bag, "/battery_runtime"))
    ctxs = [make_ctx("/battery_runtime", stamp_ns=i) for i in range(len(runtime))]
    item = columns_item(convert_run("std_msgs/msg/Float32", runtime, ctxs), "/r/battery_runtime")
    np.testing.assert_allclose(
        np.concatenate(column_rows(item, "Scalars:scalars")), [m.data for m in runtime], rtol=1e-7
    )


def joint_state(
    names: list[str], position: list[float], velocity: list[float], effort: list[float],
    stamp: int = 1_000_000_000,
) -> Any:
    return msg(
        "sensor_msgs/msg/JointState",
        header=header(stamp_ns=stamp),
        name=names,
        position=np.array(position),
        velocity=np.array(velocity),
        effort=np.array(effort),
    )


def test_joint_state_run_gives_one_column_per_joint_and_quantity() -> None:
    names = ["wheel_left_joint", "arm/elbow"]
    msgs = [joint_state(names, [0.1 * i, -0.2 * i], [1.0 + i, 2.0 + i], [], 100 + i) for i in range(3)]
    ctxs = [make_ctx("/joint_states", stamp_ns=100 + i) for i in range(3)]
    entries = convert_run("sensor_msgs/msg/JointState", msgs, ctxs)
    paths = sorted(e.path for e in entries)
    assert paths == [
        "/r/joint_states/arm\\/elbow/position",
        "/r/joint_states/arm\\/elbow/velocity",
        "/r/joint_states/wheel_left_joint/position",
        "/r/joint_states/wheel_left_joint/velocity",
    ]  # effort is empty in every message; the slash in a joint name is escaped
    left = columns_item(entries, "/r/joint_states/wheel_left_joint/position")
    np.testing.assert_allclose(
        np.concatenate(column_rows(left, "Scalars:scalars")), [0.0, 0.1, 0.2]
    )
    np.testing.assert_array_equal(left.times["ros_time"], [100, 101, 102])
    elbow = columns_item(entries, "/r/joint_states/arm\\/elbow/velocity")
    np.testing.assert_allclose(
        np.concatenate(column_rows(elbow, "Scalars:scalars")), [2.0, 3.0, 4.0]
    )
    single = convert("sensor_msgs/msg/JointState", msgs[2], ctxs[2])
    elbow = columns_item(single, "/r/joint_states/arm\\/elbow/position")
    np.testing.assert_allclose(np.concatenate(column_rows(elbow, "Scalars:scalars")), [-0.4])
    np.testing.assert_array_equal(elbow.times["ros_time"], [102])


def test_joint_state_run_with_changing_joint_sets() -> None:
    msgs = [
        joint_state(["a"], [1.0], [], [], 1),
        joint_state(["b"], [2.0], [], [], 2),
        joint_state(["a"], [3.0], [], [], 3),
    ]
    ctxs = [make_ctx("/js", stamp_ns=t) for t in (1, 2, 3)]
    entries = convert_run("sensor_msgs/msg/JointState", msgs, ctxs)
    a = columns_item(entries, "/r/js/a/position")
    np.testing.assert_array_equal(np.concatenate(column_rows(a, "Scalars:scalars")), [1.0, 3.0])
    np.testing.assert_array_equal(a.times["ros_time"], [1, 3])
    np.testing.assert_array_equal(columns_item(entries, "/r/js/b/position").times["ros_time"], [2])


def test_joint_state_length_mismatch_names_topic() -> None:
    bad = joint_state(["a", "b"], [1.0], [], [])
    with pytest.raises(ConvertError, match=r"/js: JointState has 2 names but 1 position"):
        convert("sensor_msgs/msg/JointState", bad, make_ctx("/js"))


def test_every_type_converts_a_run_at_once_and_the_fixed_layouts_read_columns() -> None:
    plotted = [row for row in REGISTRY.rows() if loaded(row.converter) in (
        scalars.NUMBER, scalars.NUMBER_ARRAY, scalars.SECONDS, scalars.TEMPERATURE,
        scalars.FLUID_PRESSURE, scalars.ILLUMINANCE, scalars.RELATIVE_HUMIDITY, scalars.BATTERY,
    )]
    assert len(plotted) == 13 + 11 + 2 + 4 + 1  # numbers, arrays, times, sensors, battery
    assert not any(isinstance(loaded(row.converter), PerMessage) for row in plotted)
    # MultiArrays vary in length and BatteryState differs between ROS 1 and 2: decoded.
    store = base_typestore()
    decoded = {row.msgtype for row in plotted if not reads_columns_only(
        loaded(row.converter), [default_message(store, row.msgtype)] * 3, make_ctx("/plot"))}
    assert decoded == {row.msgtype for row in plotted if row.msgtype.endswith("MultiArray")} | {
        "sensor_msgs/msg/BatteryState"
    }
    message = joint_state(["a"], [1.0], [2.0], [])
    assert reads_columns_only(scalars.JOINT_STATE, [message] * 3, make_ctx("/joint_states"))
