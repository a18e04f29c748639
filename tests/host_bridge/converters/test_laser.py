"""LaserScan returns Rerun receives: laser_geometry's validity rule ``range_min <= r < range_max``.

Stage and several 2D lidar drivers publish "no echo" as exactly ``range_max``; those rays must
not turn into an arc of points at the maximum range.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import rerun as rr

from host_bridge.converters.laser import convert_scan, scan_points
from tests.host_bridge.sensor_test_support import archetype, flat, header, log_item, make_ctx, msg

RANGE_MIN = np.float32(0.12)
# A float32 value that is not a round decimal, as drivers fill it (Stage: range_max 5.6).
RANGE_MAX = np.float32(5.6)
BELOW_MAX = np.nextafter(RANGE_MAX, np.float32(0.0))


def stage_scan(ranges: list[float]) -> Any:
    """A scan as Stage publishes it: quarter turns, no-echo rays set to range_max."""
    return msg(
        "sensor_msgs/msg/LaserScan",
        header=header("base_laser_link"),
        angle_min=0.0, angle_max=math.pi * 2, angle_increment=math.pi / 2,
        time_increment=0.0, scan_time=0.1,
        range_min=float(RANGE_MIN), range_max=float(RANGE_MAX),
        ranges=np.array(ranges, dtype=np.float32),
        intensities=np.zeros(len(ranges), dtype=np.float32),
    )


def test_returns_at_exactly_range_max_are_no_echo_and_dropped() -> None:
    # Rays at 0, 90, 180, 270, 360 degrees: no echo, a wall just short of the maximum, no echo,
    # a return exactly at range_min (kept: laser_geometry's lower bound is inclusive), no echo.
    ranges = [float(RANGE_MAX), float(BELOW_MAX), float(RANGE_MAX), float(RANGE_MIN), float(RANGE_MAX)]
    points, valid = scan_points(stage_scan(ranges))
    assert valid.tolist() == [False, True, False, True, False]
    np.testing.assert_allclose(
        points, [[0.0, BELOW_MAX, 0.0], [0.0, -RANGE_MIN, 0.0]], atol=1e-6
    )


def test_nan_infinities_and_too_close_returns_are_dropped_too() -> None:
    ranges = [float("nan"), float("inf"), float("-inf"), float(RANGE_MIN) / 2, 1.0]
    points, valid = scan_points(stage_scan(ranges))
    assert valid.tolist() == [False, False, False, False, True]
    np.testing.assert_allclose(points, [[1.0, 0.0, 0.0]], atol=1e-6)


def test_no_echo_rays_get_neither_points_nor_rays() -> None:
    ranges = [2.0, float(RANGE_MAX), 3.0, float(RANGE_MAX)]
    ctx = make_ctx("/base_scan", {"mode": "both"})
    entries = convert_scan(stage_scan(ranges), ctx)
    positions = flat(archetype(log_item(entries, "/r/base_scan"), rr.Points3D).positions, 3)
    np.testing.assert_allclose(positions, [[2.0, 0.0, 0.0], [-3.0, 0.0, 0.0]], atol=1e-6)
    strips = archetype(log_item(entries, "/r/base_scan/rays"), rr.LineStrips3D).strips
    ends = [strip[1] for strip in strips.as_arrow_array().to_pylist()]
    np.testing.assert_allclose(ends, [[2.0, 0.0, 0.0], [-3.0, 0.0, 0.0]], atol=1e-6)
