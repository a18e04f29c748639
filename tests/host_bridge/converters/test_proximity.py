"""Range -> sensing cone geometry in the sensor frame, plus the range scalar."""

from __future__ import annotations

import math
from itertools import pairwise
from typing import Any

import numpy as np
import pytest
import rerun as rr

from host_bridge.converters.proximity import convert_range
from tests.host_bridge.sensor_test_support import (
    archetype,
    flat,
    header,
    log_item,
    make_ctx,
    msg,
    scalars_of,
)


def reading(
    distance: float, fov: float = 0.5, low: float = 0.1, high: float = 4.0, frame_id: str = "sonar"
) -> Any:
    return msg(
        "sensor_msgs/msg/Range",
        header=header(frame_id),
        radiation_type=0,
        field_of_view=fov,
        min_range=low,
        max_range=high,
        range=distance,
    )


def cone(distance: float, **kwargs: Any) -> tuple[list[np.ndarray], float, rr.LineStrips3D]:
    """The cone's strips as (n, 3) arrays, the logged scalar, and the LineStrips3D."""
    entries = convert_range(reading(distance, **kwargs), make_ctx("/sonar"))
    item = log_item(entries, "/r/sonar")
    strips = archetype(item, rr.LineStrips3D)
    lists = strips.strips.as_arrow_array()
    offsets = lists.offsets.to_numpy()
    points = flat(lists.values, 3)
    (value,) = scalars_of(log_item(entries, "/r/sonar/range"))
    return [points[a:b] for a, b in pairwise(offsets)], value, strips


def test_cone_is_a_sector_of_the_range_around_plus_x() -> None:
    strips, value, _ = cone(2.0, fov=0.5)
    assert value == 2.0
    rim, *edges = strips
    assert len(edges) == 4
    np.testing.assert_allclose(rim[0], rim[-1], atol=1e-6)  # closed rim
    np.testing.assert_allclose(rim[:, 0], 2.0 * math.cos(0.25), rtol=1e-6)
    np.testing.assert_allclose(np.hypot(rim[:, 1], rim[:, 2]), 2.0 * math.sin(0.25), rtol=1e-5)
    for edge in edges:
        np.testing.assert_array_equal(edge[0], [0.0, 0.0, 0.0])  # apex at the sensor
        np.testing.assert_allclose(np.linalg.norm(edge[1]), 2.0, rtol=1e-6)
    item = log_item(convert_range(reading(2.0), make_ctx("/sonar")), "/r/sonar")
    assert archetype(item, rr.CoordinateFrame).frame.as_arrow_array().to_pylist() == ["r/sonar"]


def test_zero_field_of_view_is_a_segment() -> None:
    strips, _, _ = cone(3.0, fov=0.0)
    assert len(strips) == 1
    np.testing.assert_allclose(strips[0], [[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])


@pytest.mark.parametrize(
    ("distance", "scalar"),
    [(0.05, 0.05), (4.5, 4.5), (math.inf, math.nan), (-math.inf, math.nan), (math.nan, math.nan)],
)
def test_out_of_range_clears_cone_but_keeps_scalar(distance: float, scalar: float) -> None:
    strips, value, _ = cone(distance)
    assert strips == []
    np.testing.assert_equal(value, np.float64(scalar))


def test_fixed_distance_detection_draws_cone_at_max_range() -> None:
    strips, value, _ = cone(-math.inf, fov=0.0, low=0.3, high=0.3)
    np.testing.assert_allclose(strips[0], [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]], rtol=1e-6)
    assert math.isnan(value)


def test_empty_frame_id_has_no_coordinate_frame() -> None:
    item = log_item(convert_range(reading(1.0, frame_id=""), make_ctx("/sonar")), "/r/sonar")
    assert [type(a) for a in item.archetypes] == [rr.LineStrips3D]
