"""LaserScan returns Rerun receives: laser_geometry's validity rule ``range_min <= r < range_max``.

Stage and several 2D lidar drivers publish "no echo" as exactly ``range_max``; those rays must
not turn into an arc of points at the maximum range.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import rerun as rr

from host_bridge.converters.laser import SPEC, convert_scan, scan_points
from host_bridge.core.colormap import colormap_table
from host_bridge.core.contract import LogItem
from host_bridge.core.state import TopicState
from tests.host_bridge.sensor_test_support import (
    archetype,
    column_rows,
    columns_item,
    convert_run,
    flat,
    header,
    log_item,
    make_ctx,
    msg,
    rgba,
)

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


# --- the vectorised scan (cached ray tables, run form) against a per-ray reference ---------------


def scan(
    ranges: Any, *, angle_min: float = -math.pi, increment: float = math.pi / 360,
    range_min: float = 0.12, range_max: float = 12.0, intensities: Any = (),
    frame_id: str = "laser", stamp_ns: int = 1_000_000_000,
) -> Any:
    ranges = np.asarray(ranges, dtype=np.float32)
    return msg(
        "sensor_msgs/msg/LaserScan",
        header=header(frame_id, stamp_ns),
        angle_min=angle_min, angle_max=angle_min + increment * (ranges.size - 1),
        angle_increment=increment, time_increment=0.0, scan_time=0.1,
        range_min=float(np.float32(range_min)), range_max=float(np.float32(range_max)),
        ranges=ranges, intensities=np.asarray(intensities, dtype=np.float32),
    )


def reference(message: Any, by_intensity: bool = False) -> tuple[list[list[float]], list[list[int]]]:
    """Points and RGBA of one scan, ray by ray (laser_geometry's rule, turbo by range from
    range_min to range_max, or by intensity over the scan's valid intensities)."""
    table = colormap_table("turbo")
    low, high = float(message.range_min), float(message.range_max)
    rays = []
    for k, r in enumerate(message.ranges.tolist()):
        if math.isfinite(r) and np.float32(low) <= r < np.float32(high):
            angle = float(message.angle_min) + k * float(message.angle_increment)
            rays.append((k, r, angle))
    values = [float(message.intensities[k]) if by_intensity else r for k, r, _ in rays]
    if by_intensity:
        finite = [v for v in values if math.isfinite(v)]
        low, high = (min(finite), max(finite)) if finite else (math.nan, math.nan)
    points, colors = [], []
    for (_, r, angle), value in zip(rays, values, strict=True):
        points.append([r * math.cos(angle), r * math.sin(angle), 0.0])
        span = high - low if high > low else 1.0
        scaled = (value - low) / span
        scaled = 0.0 if math.isnan(scaled) else min(max(scaled, 0.0), 1.0)
        colors.append([*table[int(scaled * 255.0)].tolist(), 255])
    return points, colors


def noisy_ranges(n: int, seed: int) -> Any:
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.0, 13.0, n).astype(np.float32)  # some below min, some beyond max
    ranges[rng.random(n) < 0.05] = np.nan
    ranges[rng.random(n) < 0.05] = np.inf
    ranges[rng.random(n) < 0.02] = -np.inf
    ranges[rng.random(n) < 0.03] = np.float32(12.0)  # exactly range_max: no echo
    ranges[rng.random(n) < 0.03] = np.float32(0.12)  # exactly range_min: kept
    return ranges


def test_scan_matches_the_per_ray_reference_with_inf_nan_and_bounds() -> None:
    message = scan(noisy_ranges(720, seed=1))
    item = log_item(convert_scan(message, make_ctx("/scan")), "/r/scan")
    points = archetype(item, rr.Points3D)
    expected_points, expected_colors = reference(message)
    assert 500 < len(expected_points) < 720
    np.testing.assert_allclose(flat(points.positions, 3), expected_points, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(rgba(flat(points.colors)), expected_colors)
    assert archetype(item, rr.CoordinateFrame).frame.as_arrow_array().to_pylist() == ["r/laser"]


def test_colour_by_intensity_uses_each_scans_own_range() -> None:
    rng = np.random.default_rng(2)
    message = scan(noisy_ranges(360, seed=3), intensities=rng.uniform(10.0, 500.0, 360))
    message.intensities[5] = np.nan
    item = log_item(convert_scan(message, make_ctx("/scan", {"color_by": "intensity"})), "/r/scan")
    _, expected_colors = reference(message, by_intensity=True)
    np.testing.assert_array_equal(rgba(flat(archetype(item, rr.Points3D).colors)), expected_colors)


def run_of_scans() -> list[Any]:
    """Scans as a bag holds them: one geometry, then a changed one, a shorter scan, a scan with
    no valid return, and intensities on some scans only."""
    rng = np.random.default_rng(4)
    scans = [scan(noisy_ranges(720, seed=k), stamp_ns=(k + 1) * 100_000_000) for k in range(5)]
    scans.append(scan(noisy_ranges(720, seed=5), angle_min=0.0, increment=math.pi / 720,
                      stamp_ns=600_000_000))
    scans.append(scan(noisy_ranges(400, seed=6), stamp_ns=700_000_000))
    scans.append(scan(np.full(720, np.inf), stamp_ns=800_000_000))
    scans.append(scan(noisy_ranges(720, seed=8), intensities=rng.uniform(0, 9, 720),
                      range_min=0.5, range_max=8.0, stamp_ns=900_000_000))
    return scans


@pytest.mark.parametrize("color_by", ["range", "intensity"])
def test_run_of_scans_gives_each_scan_what_it_gives_alone(color_by: str) -> None:
    scans = run_of_scans()
    state = TopicState({"color_by": color_by, "radius": 0.05})
    ctxs = [make_ctx("/scan", stamp_ns=m.header.stamp.nanosec + m.header.stamp.sec * 10**9,
                     topic_state=state) for m in scans]
    item = columns_item(convert_run(SPEC, scans, ctxs), "/r/scan")
    positions = column_rows(item, "Points3D:positions", 3)
    colors = column_rows(item, "Points3D:colors")
    assert len(positions) == len(colors) == len(scans)
    assert [len(p) for p in positions][-2] == 0  # the scan without a valid return: empty row
    for message, ctx, row_positions, row_colors in zip(scans, ctxs, positions, colors, strict=True):
        alone = archetype(log_item(convert_scan(message, ctx), "/r/scan"), rr.Points3D)
        np.testing.assert_array_equal(row_positions, flat(alone.positions, 3))
        np.testing.assert_array_equal(row_colors, flat(alone.colors))
        expected_points, expected_colors = reference(message, by_intensity=color_by == "intensity"
                                                     and len(message.intensities) > 0)
        np.testing.assert_allclose(row_positions.reshape(-1, 3), np.reshape(expected_points, (-1, 3)),
                                   rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(rgba(row_colors), np.reshape(expected_colors, (-1, 4)))
    assert item.times["ros_time"].tolist() == [(k + 1) * 100_000_000 for k in range(len(scans))]
    radii = column_rows(item, "Points3D:radii")
    assert [r.tolist() for r in radii] == [[float(np.float32(0.05))]] * len(scans)
    frames = column_rows(item, "CoordinateFrame:frame")
    assert [r.tolist() for r in frames] == [["r/laser"]] * len(scans)


def test_run_in_rays_mode_or_with_and_without_frame_ids_goes_scan_by_scan() -> None:
    scans = run_of_scans()[:3]
    rays = convert_run(SPEC, scans, [make_ctx("/scan", {"mode": "both"}) for _ in scans])
    assert [e.path for e in rays] == ["/r/scan", "/r/scan/rays"] * 3
    scans[1].header.frame_id = ""
    mixed = convert_run(SPEC, scans, [make_ctx("/scan") for _ in scans])
    kinds = [[type(a) for a in e.archetypes] if isinstance(e, LogItem) else None for e in mixed]
    with_frame = [rr.Points3D, rr.CoordinateFrame]
    assert kinds == [with_frame, [rr.Points3D], with_frame]


def test_infinite_bounds_still_drop_nan_and_infinite_ranges() -> None:
    message = scan([float("nan"), float("inf"), float("-inf"), 1.0], range_min=-math.inf,
                   range_max=math.inf)
    points, valid = scan_points(message)
    assert valid.tolist() == [False, False, False, True]
    assert points.shape == (1, 3)
