"""Segment geometry: the merge's rules and invariants, corner joining, the box mesh and the
occupancy image the edge detector sees."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from host_bridge.converters.segments import (
    detect_segments,
    join_corners,
    merge_segments,
    occupied_mask,
    segments_to_mesh,
)
from host_bridge.converters.walls import wall_segments
from tests.host_bridge.converters.test_walls import RES, as_grid, default_options, floor_plan

Float64Array = npt.NDArray[np.float64]


def merge(segments: npt.ArrayLike, **overrides: float) -> Float64Array:
    settings = {"angle_deg": 5.0, "distance": 0.225, "gap": 0.35} | overrides
    return merge_segments(segments, **settings)


def test_merged_wall_is_all_endpoints_projected_on_the_weighted_line() -> None:
    # Lengths 2 and 1: the centroid line sits at y = (2 * 0 + 1 * 0.1) / 3.
    out = merge([[0.0, 0.0, 2.0, 0.0], [3.1, 0.1, 2.1, 0.1]])
    np.testing.assert_allclose(out, [[0.0, 0.1 / 3, 3.1, 0.1 / 3]], atol=1e-12)


def test_vertical_fragments_merge_into_one_vertical_wall() -> None:
    out = merge([[1.0, 0.0, 1.0, 1.0], [1.04, 2.0, 1.04, 1.1], [1.0, 2.05, 1.0, 3.0]])
    # Length-weighted centroid x: (1.0 * 1 + 1.04 * 0.9 + 1.0 * 0.95) / 2.85.
    x = (1.0 + 1.04 * 0.9 + 0.95) / 2.85
    np.testing.assert_allclose(out, [[x, 0.0, x, 3.0]], atol=1e-12)


@pytest.mark.parametrize(
    "pair",
    [
        [[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],  # an L corner
        [[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 1.0 + math.cos(0.2), math.sin(0.2)]],  # 11.5 degree bend
        [[0.0, 0.0, 2.0, 0.0], [0.0, 0.3, 2.0, 0.3]],  # parallel walls 0.3 m apart
        [[0.0, 0.0, 1.0, 0.0], [1.9, 0.0, 3.0, 0.0]],  # a 0.9 m door between collinear walls
    ],
)
def test_merge_leaves_walls_that_are_not_one_wall_alone(pair: list[list[float]]) -> None:
    out = merge(pair)
    assert out.shape == (2, 4)
    expected = {tuple(sorted([(a, b), (c, d)])) for a, b, c, d in pair}
    assert {tuple(sorted([(a, b), (c, d)])) for a, b, c, d in out.tolist()} == expected


def test_fragment_between_parallel_walls_joins_its_own_wall() -> None:
    # Both edges of wall A (y = 0) and of wall B (y = 0.3), plus a piece of B's lower edge past
    # the end of B. That piece is nearer to A's upper edge (0.2 m) than to B's (0.3 m along), so
    # it must not be merged into A along with A's own edges.
    out = merge(
        [
            [0.0, -0.05, 3.0, -0.05],
            [0.0, 0.05, 3.0, 0.05],
            [0.0, 0.35, 2.0, 0.35],
            [0.0, 0.25, 2.0, 0.25],
            [2.3, 0.25, 3.0, 0.25],
        ]
    )
    # B's centroid line: (2 * 0.35 + 2 * 0.25 + 0.7 * 0.25) / 4.7.
    b = (0.7 + 0.5 + 0.175) / 4.7
    np.testing.assert_allclose(out, [[0.0, 0.0, 3.0, 0.0], [0.0, b, 3.0, b]], atol=1e-12)


def test_segments_that_merge_with_nothing_come_out_bit_exact() -> None:
    lone = [0.123456789, 5.2, 1.987654321, 6.3]
    out = merge([[0.0, 0.0, 1.0, 0.0], [1.1, 0.0, 2.0, 0.0], lone])
    assert out.shape == (2, 4)
    assert lone in out.tolist()


def test_merge_ignores_input_order_and_merging_again_changes_nothing() -> None:
    # The pieces the detector finds on the test plan, each cut in three overlapping fragments
    # and nudged across by up to a tenth of a cell, as an edge detector's would be.
    pixels = detect_segments(occupied_mask(floor_plan()), default_options().detector(RES))
    rng = np.random.default_rng(5)
    cuts = [(0.0, 0.4), (0.35, 0.7), (0.65, 1.0)]
    pieces = [
        np.concatenate([p[:2] + a * (p[2:] - p[:2]), p[:2] + b * (p[2:] - p[:2])])
        for p in pixels
        for a, b in cuts
    ]
    raw = (np.array(pieces) + rng.uniform(-0.1, 0.1, (len(pieces), 4)) + 0.5) * RES
    out = merge(raw)
    assert out.shape[0] < raw.shape[0] / 2
    rng = np.random.default_rng(3)
    shuffled = raw[rng.permutation(raw.shape[0])]
    flip = rng.random(raw.shape[0]) < 0.5
    shuffled[flip] = shuffled[flip][:, [2, 3, 0, 1]]
    np.testing.assert_array_equal(merge(shuffled), out)
    np.testing.assert_array_equal(merge(out), out)


def test_join_corners_extends_short_ends_to_the_crossing_wall() -> None:
    segs = np.array(
        [
            [0.1, 0.0, 2.0, 0.0],  # L corner with the next wall, 0.1 m short
            [0.0, 0.12, 0.0, 2.0],
            [1.0, 0.08, 1.0, 1.0],  # T junction onto the first wall, 0.08 m short
            [3.0, 0.0, 3.0, 1.0],  # 1 m past the first wall's end: out of reach
        ]
    )
    out = join_corners(segs, reach=0.2)
    np.testing.assert_allclose(
        out,
        [[0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 2.0], [1.0, 0.0, 1.0, 1.0], [3.0, 0.0, 3.0, 1.0]],
        atol=1e-12,
    )


def test_box_mesh_geometry_and_pose() -> None:
    height, thickness = 0.5, 0.1
    yaw = math.pi / 2
    mesh = segments_to_mesh(
        [[0.0, 0.0, 2.0, 0.0]],
        [1.0, 2.0, 0.0],
        [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)],
        height,
        thickness,
    )
    assert mesh.vertices.shape == (24, 3)
    assert mesh.triangles.shape == (12, 3)
    # Local box: x in [-t/2, 2 + t/2], y in [-t/2, t/2]; turned 90 degrees, (x, y) -> (-y, x).
    corners = {
        (1.0 - y, 2.0 + x, z)
        for x in (-0.05, 2.05)
        for y in (-0.05, 0.05)
        for z in (0.0, height)
    }
    found = {tuple(np.round(v, 6)) for v in mesh.vertices.astype(np.float64).tolist()}
    assert found == {tuple(np.round(c, 6)) for c in corners}
    # Normals are unit, face outwards and agree with the triangle winding.
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-6)
    tri = mesh.vertices[mesh.triangles].astype(np.float64)
    winding = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    winding /= np.linalg.norm(winding, axis=1, keepdims=True)
    np.testing.assert_allclose(winding, mesh.normals[mesh.triangles[:, 0]], atol=1e-6)
    centre = mesh.vertices.mean(axis=0)
    assert ((tri.mean(axis=1) - centre) * winding).sum(axis=1).min() > 0.0


def test_occupied_mask_marks_wall_values_only() -> None:
    cells = np.array([[-1, 0, 64, 65, 100, 101, -50]], dtype=np.int8)
    assert occupied_mask(cells).tolist() == [[0, 0, 0, 1, 1, 0, 0]]
    assert occupied_mask(cells, occupied_threshold=50).tolist() == [[0, 0, 1, 1, 1, 0, 0]]


def test_walls_of_a_plan_inside_a_large_unknown_map_are_found_where_it_lies() -> None:
    # Detection works on the part of the image around occupied cells only; a small plan at an
    # odd place of a mostly unknown 1500x1300 map must give its walls there, as it does alone.
    plan = floor_plan()
    row, col = 1031, 517
    large = np.full((1500, 1300), -1, dtype=np.int8)
    large[row : row + plan.shape[0], col : col + plan.shape[1]] = plan
    alone = wall_segments(as_grid(plan), default_options())
    placed = wall_segments(as_grid(large), default_options()) - np.array([col, row, col, row]) * RES
    assert placed.shape == alone.shape == (6, 4)
    for segment in alone:
        errors = [max(np.hypot(*(segment[:2] - p[:2])), np.hypot(*(segment[2:] - p[2:]))) for p in placed]
        assert min(errors) <= RES  # the same wall, within a cell


def test_an_image_without_occupied_cells_has_no_segments() -> None:
    mask = occupied_mask(np.array([[-1, 0, 0], [0, -1, 50]], dtype=np.int8))
    assert detect_segments(mask, default_options().detector(RES)).shape == (0, 4)
