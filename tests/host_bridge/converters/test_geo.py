"""NavSatFix -> GeoPoints (radius from covariance) and altitude scalars."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from host_bridge.converters.geo import SPEC
from tests.host_bridge.sensor_test_support import (
    column_rows,
    columns_item,
    convert,
    convert_run,
    header,
    make_ctx,
    msg,
    read_topic,
    reads_columns_only,
    stamp_ns,
)


def fix(
    lat: float,
    lon: float,
    *,
    alt: float = 10.0,
    status: int = 0,
    covariance: float = 4.0,
    covariance_type: int = 2,
    stamp: int = 1_000_000_000,
) -> Any:
    return msg(
        "sensor_msgs/msg/NavSatFix",
        header=header("gps", stamp),
        status=msg("sensor_msgs/msg/NavSatStatus", status=status, service=1),
        latitude=lat,
        longitude=lon,
        altitude=alt,
        position_covariance=np.array([covariance, 0, 0, 0, 2 * covariance, 0, 0, 0, 9.0]),
        position_covariance_type=covariance_type,
    )


def test_real_track_first_fix_and_radii(shared_data: Path) -> None:
    msgs = list(read_topic(shared_data / "gps_fix_rviz_satellite" / "sample.bag", "/gps/fix"))
    assert len(msgs) == 151
    ctxs = [make_ctx("/gps/fix", stamp_ns=stamp_ns(m)) for m in msgs]
    entries = convert_run(SPEC, msgs, ctxs)
    points = columns_item(entries, "/r/gps/fix")
    positions = np.concatenate(column_rows(points, "GeoPoints:positions", 2))
    assert positions.shape == (151, 2)
    np.testing.assert_array_equal(positions[0], [msgs[0].latitude, msgs[0].longitude])
    np.testing.assert_allclose(positions.mean(axis=0), [39.951, -75.190], atol=0.002)
    radii = np.concatenate(column_rows(points, "GeoPoints:radii"))
    expected = [math.sqrt(max(m.position_covariance[0], m.position_covariance[4])) for m in msgs]
    np.testing.assert_allclose(radii, expected, rtol=1e-6)
    assert (radii > 0).all()  # metres, not UI points: the covariance type is known (2)
    np.testing.assert_array_equal(points.times["ros_time"], [stamp_ns(m) for m in msgs])
    altitude = columns_item(entries, "/r/gps/fix/altitude")
    np.testing.assert_array_equal(
        np.concatenate(column_rows(altitude, "Scalars:scalars")), [m.altitude for m in msgs]
    )


def test_no_fix_and_nan_are_skipped_unknown_covariance_is_ui_points() -> None:
    msgs = [
        fix(59.3, 18.0, stamp=1),
        fix(59.4, 18.1, status=-1, stamp=2),  # STATUS_NO_FIX
        fix(math.nan, 18.2, stamp=3),
        fix(59.5, 18.3, alt=math.nan, covariance_type=0, stamp=4),
    ]
    ctxs = [make_ctx("/fix", {"radius": 7.0}, stamp_ns=i + 1) for i in range(4)]
    entries = convert_run(SPEC, msgs, ctxs)
    points = columns_item(entries, "/r/fix")
    np.testing.assert_allclose(
        np.concatenate(column_rows(points, "GeoPoints:positions", 2)), [[59.3, 18.0], [59.5, 18.3]]
    )
    # Known covariance: sqrt of the larger horizontal variance (8) in metres; unknown: -7 UI points.
    np.testing.assert_allclose(
        np.concatenate(column_rows(points, "GeoPoints:radii")), [math.sqrt(8.0), -7.0], rtol=1e-6
    )
    np.testing.assert_array_equal(points.times["ros_time"], [1, 4])
    altitude = columns_item(entries, "/r/fix/altitude")
    np.testing.assert_array_equal(np.concatenate(column_rows(altitude, "Scalars:scalars")), [10.0])
    np.testing.assert_array_equal(altitude.times["ros_time"], [1])


def test_single_fix_and_no_fix_message() -> None:
    entries = convert(SPEC, fix(40.0, -75.0, alt=3.5), make_ctx("/fix"))
    assert [e.path for e in entries] == ["/r/fix", "/r/fix/altitude"]
    assert convert(SPEC, fix(40.0, -75.0, status=-1), make_ctx("/fix")) == []
    assert reads_columns_only(SPEC, [fix(40.0, -75.0, alt=3.5)] * 2, make_ctx("/fix"))
