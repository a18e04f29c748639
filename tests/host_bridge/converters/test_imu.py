"""Imu and MagneticField -> orientation transform, arrows and scalar columns."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr

from host_bridge.converters.imu import IMU, MAGNETIC_FIELD
from host_bridge.core.contract import ColumnsItem, LogItem
from tests.host_bridge.sensor_test_support import (
    archetype,
    column_rows,
    columns_item,
    convert,
    convert_run,
    flat,
    header,
    make_ctx,
    msg,
    read_topic,
    reads_columns_only,
    rgba,
    stamp_ns,
)

BAG = ("phidgets_imu_ccny", "phidgets_imu_upside_down.bag")


def vector(x: float, y: float, z: float) -> Any:
    return msg("geometry_msgs/msg/Vector3", x=x, y=y, z=z)


def imu(
    q: tuple[float, float, float, float],
    *,
    gyro: tuple[float, float, float] = (0.1, 0.2, 0.3),
    accel: tuple[float, float, float] = (0.0, 0.0, 9.81),
    covariance0: float = 0.0,
    frame_id: str = "imu",
    stamp: int = 1_000_000_000,
) -> Any:
    x, y, z, w = q
    return msg(
        "sensor_msgs/msg/Imu",
        header=header(frame_id, stamp),
        orientation=msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w),
        orientation_covariance=np.array([covariance0] + [0.0] * 8),
        angular_velocity=vector(*gyro),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector(*accel),
        linear_acceleration_covariance=np.zeros(9),
    )


@pytest.fixture(scope="module")
def phidgets(shared_data: Path) -> dict[str, list[Any]]:
    bag = shared_data.joinpath(*BAG)
    return {topic: list(read_topic(bag, topic)) for topic in ("/imu/data_raw", "/imu/mag")}


def test_real_zero_quaternion_run_has_no_nan_and_keeps_scalars(
    phidgets: dict[str, list[Any]],
) -> None:
    msgs = phidgets["/imu/data_raw"]
    assert len(msgs) == 13964
    assert all(m.orientation.w == 0.0 for m in msgs[:10])  # the bag's invalid orientation
    ctxs = [make_ctx("/imu/data_raw", stamp_ns=stamp_ns(m)) for m in msgs]
    started = time.perf_counter()
    entries = convert_run(IMU, msgs, ctxs)
    assert time.perf_counter() - started < 5.0
    orientation = columns_item(entries, "/r/imu/data_raw/orientation")
    quaternions = np.concatenate(column_rows(orientation, "Transform3D:quaternion", 4))
    np.testing.assert_array_equal(quaternions, np.tile([0.0, 0.0, 0.0, 1.0], (13964, 1)))
    arrows = column_rows(orientation, "Arrows3D:vectors", 3)
    assert len(arrows) == 13964
    assert all(a.shape == (2, 3) for a in arrows[:5])
    assert np.isfinite(np.concatenate(arrows)).all()
    assert set(np.concatenate(column_rows(orientation, "Transform3D:parent_frame"))) == {"r/imu"}
    np.testing.assert_array_equal(orientation.times["ros_time"], [stamp_ns(m) for m in msgs])
    accel = columns_item(entries, "/r/imu/data_raw/linear_acceleration")
    gyro = columns_item(entries, "/r/imu/data_raw/angular_velocity")
    accel_rows = np.stack(column_rows(accel, "Scalars:scalars"))
    gyro_rows = np.stack(column_rows(gyro, "Scalars:scalars"))
    assert accel_rows.shape == gyro_rows.shape == (13964, 3)
    first = msgs[0]
    np.testing.assert_array_equal(
        accel_rows[0],
        [first.linear_acceleration.x, first.linear_acceleration.y, first.linear_acceleration.z],
    )
    np.testing.assert_array_equal(
        gyro_rows[-1],
        [msgs[-1].angular_velocity.x, msgs[-1].angular_velocity.y, msgs[-1].angular_velocity.z],
    )
    assert np.isfinite(accel_rows).all()
    assert np.isfinite(gyro_rows).all()
    assert -10.5 < accel_rows[:, 2].mean() < -9.0  # upside down: gravity reads -g on z


def test_real_magnetic_field_run(phidgets: dict[str, list[Any]]) -> None:
    msgs = phidgets["/imu/mag"]
    ctxs = [make_ctx("/imu/mag", stamp_ns=stamp_ns(m)) for m in msgs]
    spec = MAGNETIC_FIELD
    assert reads_columns_only(spec, msgs[:4], make_ctx("/imu/mag"))
    entries = convert_run(spec, msgs, ctxs)
    item = columns_item(entries, "/r/imu/mag")
    rows = np.stack(column_rows(item, "Scalars:scalars"))
    # Every other message of this magnetometer is NaN, NaN, NaN: "no new reading", not plotted.
    readings = [m for m in msgs if not math.isnan(m.magnetic_field.x)]
    assert rows.shape == (6974, 3)
    expected = [[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z] for m in readings]
    np.testing.assert_array_equal(rows, expected)
    assert item.times["ros_time"].tolist() == [stamp_ns(m) for m in readings]
    legends = [e for e in entries if isinstance(e, LogItem) and e.static]
    assert [e.path for e in legends] == ["/r/imu/mag"]
    names = archetype(legends[0], rr.SeriesLines).names.as_arrow_array().to_pylist()
    assert names == ["x", "y", "z"]


def test_valid_orientation_is_normalised_and_arrows_scaled() -> None:
    half = math.sqrt(0.5)
    ctx = make_ctx("/imu", {"acceleration_scale": 0.5, "angular_velocity_scale": 2.0})
    entries = convert(IMU, imu((0.0, 0.0, 2 * half, 2 * half)), ctx)  # 90 deg yaw, norm 2
    orientation = columns_item(entries, "/r/imu/orientation")
    (q,) = column_rows(orientation, "Transform3D:quaternion", 4)
    np.testing.assert_allclose(q, [[0.0, 0.0, half, half]], rtol=1e-6)
    (arrows,) = column_rows(orientation, "Arrows3D:vectors", 3)
    np.testing.assert_allclose(arrows, [[0.0, 0.0, 4.905], [0.2, 0.4, 0.6]], rtol=1e-6)
    assert {c.component_descriptor().component for c in orientation.columns} == {
        "Transform3D:quaternion", "Transform3D:parent_frame", "Arrows3D:vectors"
    }
    statics = [e for e in entries if isinstance(e, LogItem) and e.static]
    axes = [e for e in statics if e.path == "/r/imu/orientation"]
    assert len(axes) == 1
    # The arrows' labels and colours are the same in every row: static, with the axes.
    arrow_style = archetype(axes[0], rr.Arrows3D)
    assert arrow_style.labels.as_arrow_array().to_pylist() == ["linear_acceleration", "angular_velocity"]
    assert rgba(flat(arrow_style.colors)).tolist() == [[255, 170, 0, 255], [170, 80, 255, 255]]
    assert arrow_style.vectors is None
    # Legends and axes are sent once per topic, not with every message.
    again = convert(IMU, imu((0.0, 0.0, 0.0, 1.0)), ctx)
    assert not [e for e in again if isinstance(e, LogItem)]
    assert all(isinstance(e, ColumnsItem) for e in again)


@pytest.mark.parametrize(
    ("q", "covariance0"),
    [
        ((0.0, 0.0, 0.0, 0.0), 0.0),
        ((0.3, 0.1, 0.0, 0.9), -1.0),  # REP 145: covariance[0] = -1 means "no orientation"
        ((math.nan, 0.0, 0.0, 1.0), 0.0),
        ((math.inf, 0.0, 0.0, 1.0), 0.0),
    ],
)
def test_missing_orientation_becomes_identity_not_nan(
    q: tuple[float, float, float, float], covariance0: float
) -> None:
    entries = convert(IMU, imu(q, covariance0=covariance0), make_ctx("/imu"))
    orientation = columns_item(entries, "/r/imu/orientation")
    (quaternion,) = column_rows(orientation, "Transform3D:quaternion", 4)
    np.testing.assert_array_equal(quaternion, [[0.0, 0.0, 0.0, 1.0]])
    (gyro,) = column_rows(columns_item(entries, "/r/imu/angular_velocity"), "Scalars:scalars")
    np.testing.assert_allclose(gyro, [0.1, 0.2, 0.3])


def test_run_with_mixed_orientations_and_empty_frame_id() -> None:
    msgs = [
        imu((0.0, 0.0, 0.0, 0.0), frame_id="", stamp=1),
        imu((0.0, 1.0, 0.0, 0.0), frame_id="", stamp=2),
    ]
    entries = convert_run(IMU, msgs, [make_ctx("/imu", stamp_ns=1), make_ctx("/imu", stamp_ns=2)])
    orientation = columns_item(entries, "/r/imu/orientation")
    quaternions = np.concatenate(column_rows(orientation, "Transform3D:quaternion", 4))
    np.testing.assert_array_equal(quaternions, [[0, 0, 0, 1], [0, 1, 0, 0]])
    # No frame id: the orientation hangs under the topic entity's implicit frame.
    parents = np.concatenate(column_rows(orientation, "Transform3D:parent_frame"))
    assert list(parents) == ["tf#/r/imu", "tf#/r/imu"]
    np.testing.assert_array_equal(orientation.times["ros_time"], [1, 2])


def test_magnetic_field_without_a_reading_logs_nothing() -> None:
    nan = float("nan")
    spec = MAGNETIC_FIELD

    def field(x: float, y: float, z: float) -> Any:
        return msg("sensor_msgs/msg/MagneticField", header=header("imu"),
                   magnetic_field=vector(x, y, z), magnetic_field_covariance=np.zeros(9))

    entries = convert(spec, field(nan, nan, nan), make_ctx("/imu/mag"))
    assert [e for e in entries if not (isinstance(e, LogItem) and e.static)] == []
    partial = convert(spec, field(1e-5, nan, 3e-5), make_ctx("/imu/mag"))
    (item,) = [e for e in partial if isinstance(e, ColumnsItem)]
    np.testing.assert_array_equal(column_rows(item, "Scalars:scalars"), [[1e-5, nan, 3e-5]])
