"""The apartment's geometry: exact ray casting against wall segments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host_bridge.demo import world


def test_cast_rays_single_wall_is_exact() -> None:
    wall = np.array([[[2.0, -10.0], [2.0, 10.0]]])
    ranges = world.cast_rays((0.0, 0.0), 0.0, [0.0, math.pi / 4, -math.pi / 4], wall, 3.5)
    np.testing.assert_allclose(
        ranges, [2.0, 2.0 * math.sqrt(2.0), 2.0 * math.sqrt(2.0)], rtol=1e-12
    )
    # yaw and origin both count: from (0.5, 1) turned 45 degrees left, the wall is 1.5*sqrt(2) away
    turned = world.cast_rays((0.5, 1.0), math.pi / 4, [0.0], wall, 3.5)
    np.testing.assert_allclose(turned, [1.5 * math.sqrt(2.0)], rtol=1e-12)


def test_cast_rays_misses_are_inf_and_nearest_wall_wins() -> None:
    walls = np.array([[[2.0, -10.0], [2.0, 10.0]], [[1.0, -0.5], [1.0, 0.5]]])
    # backwards: nothing; 1.2 rad: the long wall is 2/cos(1.2) = 5.5 m away, past max range;
    # straight ahead: the short wall at 1 m hides the long one at 2 m
    ranges = world.cast_rays((0.0, 0.0), 0.0, [math.pi, 1.2, 0.0], walls, 3.5)
    assert ranges[0] == math.inf
    assert ranges[1] == math.inf
    assert ranges[2] == pytest.approx(1.0, abs=1e-12)
    _, index = world.ray_hits((0.0, 0.0), [math.pi, 0.0], walls, 3.5)
    assert index.tolist() == [-1, 1]
    # a ray along a segment (parallel) never hits it
    assert world.cast_rays((0.0, 0.0), math.pi / 2, [0.0], walls[:1] - [2.0, 0.0], 3.5)[0] == math.inf
