"""Wall extraction: segments against drawn walls and how the wall mesh lines up with the GridMap
of the same grid (the geometry's own rules are tests/host_bridge/converters/test_segments.py)."""

from __future__ import annotations

import importlib
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import rerun as rr
import yaml

from host_bridge.converters import occupancy, walls
from host_bridge.core.contract import LogItem
from host_bridge.core.options import GridOptions
from host_bridge.core.state import Grid
from tests.host_bridge.converters.test_occupancy import grid_msg, shared_contexts, update_msg
from tests.host_bridge.sensor_test_support import archetype, flat, log_item, make_ctx

Float64Array = npt.NDArray[np.float64]

RES = 0.05
ORIGIN = (-3.0, -2.0, 0.0)
# Walls drawn one cell thick, as (col0, row0, col1, row1) cells: an L corner, two parallel walls
# 6 cells (0.3 m) apart, a wall at atan2(36, 48) = 36.87 degrees, a vertical wall.
TRUTH_CELLS = {
    "corner_x": (20, 20, 80, 20),
    "corner_y": (20, 20, 20, 80),
    "parallel_a": (110, 30, 180, 30),
    "parallel_b": (110, 36, 180, 36),
    "diagonal": (100, 60, 148, 96),
    "vertical": (180, 60, 180, 140),
}
# Grid-local metres of the cell centres the walls run through.
TRUTH = {name: (np.array(cells, dtype=np.float64) + 0.5) * RES for name, cells in TRUTH_CELLS.items()}


def floor_plan(names: tuple[str, ...] = tuple(TRUTH_CELLS)) -> npt.NDArray[np.int8]:
    """Free 200x160 grid with the named walls, and an unknown block whose frontier is no wall."""
    mask = np.zeros((160, 200), dtype=np.uint8)
    for name in names:
        x0, y0, x1, y1 = TRUTH_CELLS[name]
        cv2.line(mask, (x0, y0), (x1, y1), 255, 1)
    cells = np.zeros((160, 200), dtype=np.int8)
    cells[110:150, 30:80] = -1
    cells[mask > 0] = 100
    return cells


def default_options() -> walls.WallOptions:
    return walls.WallOptions.from_options(GridOptions(), RES, "/map")


def as_grid(cells: npt.NDArray[np.int8]) -> Grid:
    return occupancy.grid_from_msg(grid_msg(cells, resolution=RES), make_ctx("/map"))


@pytest.fixture(scope="module")
def segments() -> Float64Array:
    return walls.wall_segments(as_grid(floor_plan()), default_options())


def endpoint_error(segment: Float64Array, truth: Float64Array) -> float:
    """Largest endpoint distance, for the better of the two endpoint pairings."""
    straight = max(np.hypot(*(segment[:2] - truth[:2])), np.hypot(*(segment[2:] - truth[2:])))
    crossed = max(np.hypot(*(segment[:2] - truth[2:])), np.hypot(*(segment[2:] - truth[:2])))
    return float(min(straight, crossed))


def matched(segments: Float64Array) -> dict[str, Float64Array]:
    return {
        name: min(segments, key=lambda s: endpoint_error(s, truth)) for name, truth in TRUTH.items()
    }


def angle_deg(segment: Float64Array) -> float:
    return math.degrees(math.atan2(segment[3] - segment[1], segment[2] - segment[0])) % 180.0


def test_walls_match_the_drawn_walls_within_one_cell(segments: Float64Array) -> None:
    # One segment per wall: no double edges, no frontier of the unknown block, nothing extra.
    assert segments.shape == (6, 4)
    found = matched(segments)
    assert len({tuple(s) for s in found.values()}) == 6
    for name, segment in found.items():
        assert endpoint_error(segment, TRUTH[name]) <= RES, name


def test_corner_is_not_folded_and_parallel_walls_stay_apart(segments: Float64Array) -> None:
    found = matched(segments)
    assert angle_deg(found["corner_x"]) == pytest.approx(0.0, abs=0.5)
    assert angle_deg(found["corner_y"]) == pytest.approx(90.0, abs=0.5)
    a, b = found["parallel_a"], found["parallel_b"]
    assert angle_deg(a) == pytest.approx(0.0, abs=0.5)
    assert angle_deg(b) == pytest.approx(0.0, abs=0.5)
    assert (a[1] + a[3]) / 2 - (b[1] + b[3]) / 2 == pytest.approx(-0.3, abs=RES / 2)


def test_diagonal_angle_and_vertical_wall(segments: Float64Array) -> None:
    found = matched(segments)
    assert angle_deg(found["diagonal"]) == pytest.approx(math.degrees(math.atan2(36, 48)), abs=2.0)
    vertical = found["vertical"]
    assert vertical[0] == pytest.approx(vertical[2], abs=1e-9)
    assert vertical[0] == pytest.approx(TRUTH["vertical"][0], abs=RES / 2)


def test_thick_walls_meet_at_corners_and_junctions() -> None:
    # Two-cell walls: an L corner and a T junction whose edges stop at the crossing wall.
    cells = np.zeros((120, 120), dtype=np.int8)
    cells[20:22, 20:90] = 100
    cells[20:90, 20:22] = 100
    cells[60:62, 20:90] = 100
    segments = walls.wall_segments(as_grid(cells), default_options()) / RES - 0.5
    assert segments.shape == (3, 4)
    vertical = segments[np.abs(segments[:, 0] - segments[:, 2]) < 1.0][0]
    top, stem = sorted(segments[np.abs(segments[:, 1] - segments[:, 3]) < 1.0].tolist())
    # All three centre lines within a cell of the walls' centres (20.5 and 60.5 in cells) ...
    assert vertical[0] == pytest.approx(20.5, abs=1.0)
    assert top[1] == pytest.approx(20.5, abs=1.0)
    assert stem[1] == pytest.approx(60.5, abs=1.0)
    # ... and joined: the corner is one point, the stem starts on the vertical wall's line.
    assert min(vertical[1], vertical[3]) == pytest.approx(top[1], abs=1e-9)
    assert top[0] == pytest.approx(vertical[0], abs=1e-9)
    assert stem[0] == pytest.approx(vertical[0], abs=1e-9)


def point_segment_distance(points: Float64Array, segment: Float64Array) -> Float64Array:
    a, b = segment[:2], segment[2:]
    t = np.clip(((points - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    distance: Float64Array = np.hypot(*(points - (a + t[:, None] * (b - a))).T)
    return distance


def yaw_matrix(quaternion: Float64Array) -> Float64Array:
    yaw = 2.0 * math.atan2(quaternion[2], quaternion[3])
    return np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0])
def test_wall_mesh_stands_on_the_occupied_cells_of_the_grid_map(yaw_deg: float) -> None:
    cells = floor_plan()
    message = grid_msg(cells, resolution=RES, origin=ORIGIN, yaw=math.radians(yaw_deg))
    ctx = make_ctx("/map")
    grid_map = archetype(log_item(occupancy.convert_grid(message, ctx), "/r/map"), rr.GridMap)
    item = log_item(walls.wall_items(message, ctx), "/r/map/walls")
    assert flat(archetype(item, rr.CoordinateFrame).frame).tolist() == ["r/map"]
    mesh = archetype(item, rr.Mesh3D)
    vertices = flat(mesh.vertex_positions, 3).astype(np.float64)
    assert vertices.shape == (6 * 24, 3)
    options = default_options()
    assert vertices[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    assert vertices[:, 2].max() == pytest.approx(options.height, abs=1e-6)

    # The GridMap as logged: grid-local (x, y) -> map frame.
    translation = flat(grid_map.translation, 3)[0, :2].astype(np.float64)
    rotation = yaw_matrix(flat(grid_map.quaternion, 4)[0].astype(np.float64))
    cell_size = float(flat(grid_map.cell_size)[0])
    truth_in_map = {
        name: np.concatenate([rotation @ t[:2] + translation, rotation @ t[2:] + translation])
        for name, t in TRUTH.items()
    }
    boxes = vertices[:, :2].reshape(6, 24, 2)
    for box in boxes:
        # Every vertex of a box lies within half the thickness (and a cell) of one drawn wall.
        nearest = min(
            truth_in_map.values(), key=lambda t: point_segment_distance(box, t).max()
        )
        assert point_segment_distance(box, nearest).max() <= options.thickness / 2 + RES + 1e-6
        # Its centre line, mapped back through the GridMap pose, runs over occupied cells.
        start, end = box[0:2].mean(axis=0), box[2:4].mean(axis=0)
        line = start + np.linspace(0.0, 1.0, 25)[:, None] * (end - start)
        col, row = np.floor((line - translation) @ rotation / cell_size).astype(int).T
        near = np.stack([cells[row + dy, col + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        assert (near == 100).any(axis=0).all()
    # And every drawn wall has its box.
    for truth in truth_in_map.values():
        assert min(point_segment_distance(box, truth).max() for box in boxes) <= 0.05 + RES


def test_unchanged_grid_yields_nothing_and_a_grid_without_walls_clears() -> None:
    ctx = make_ctx("/map")
    first = walls.wall_items(grid_msg(floor_plan()), ctx)
    assert len(first) == 1
    assert walls.wall_items(grid_msg(floor_plan()), ctx) == []
    for empty in (np.zeros((160, 200), dtype=np.int8), np.zeros((0, 0), dtype=np.int8)):
        cleared = walls.wall_items(grid_msg(empty), ctx)
        assert [(e.path, [type(a) for a in e.archetypes]) for e in cleared if isinstance(e, LogItem)] == [
            ("/r/map/walls", [rr.Clear])
        ]


@pytest.mark.parametrize(
    ("topic", "options", "boxes"),
    [
        ("/map", {}, 6),
        ("/robot/map", {}, 6),
        ("/map", {"walls": False}, 0),
        ("/global_costmap/costmap", {}, 0),
        ("/global_costmap/costmap", {"walls": True}, 6),
    ],
)
def test_walls_are_on_by_default_only_for_map_topics(
    topic: str, options: dict[str, Any], boxes: int
) -> None:
    entries = walls.wall_items(grid_msg(floor_plan()), make_ctx(topic, options))
    if boxes == 0:
        assert entries == []
    else:
        mesh = archetype(log_item(entries, f"/r{topic}/walls"), rr.Mesh3D)
        assert flat(mesh.vertex_positions, 3).shape == (boxes * 24, 3)


def test_update_rebuilds_the_walls_of_the_patched_grid() -> None:
    grid_ctx, update_ctx = shared_contexts("/map", "/map_updates")
    corner = grid_msg(floor_plan(("corner_x", "corner_y")))
    occupancy.convert_grid(corner, grid_ctx)
    first = archetype(log_item(walls.wall_items(corner, grid_ctx), "/r/map/walls"), rr.Mesh3D)
    assert flat(first.vertex_positions, 3).shape == (2 * 24, 3)
    # The update carries the vertical wall; its walls go to the grid's wall entity.
    full = floor_plan(("corner_x", "corner_y", "vertical"))
    patch = update_msg(170, 50, full[50:150, 170:190])
    occupancy.convert_update(patch, update_ctx)
    entries = walls.update_wall_items(patch, update_ctx)
    mesh = archetype(log_item(entries, "/r/map/walls"), rr.Mesh3D)
    assert flat(mesh.vertex_positions, 3).shape == (3 * 24, 3)


def cell_segments(cells: npt.NDArray[np.int8]) -> Float64Array:
    """Walls of ``cells`` in cell units (cell centres at integers)."""
    return walls.wall_segments(as_grid(cells), default_options()) / RES - 0.5


def test_floor_plan_walls_have_exact_endpoints() -> None:
    # One-cell walls: a room with a door in its bottom wall and an inner wall from the top.
    cells = np.zeros((80, 100), dtype=np.int8)
    cells[10, 10:91] = 100
    cells[70, 10:91] = 100
    cells[70, 40:58] = 0  # the door, 18 cells
    cells[10:71, 10] = 100
    cells[10:71, 90] = 100
    cells[10:41, 50] = 100
    found = {tuple(s) for s in np.round(cell_segments(cells), 9).tolist()}
    assert found == {
        (10.0, 10.0, 90.0, 10.0),  # top
        (10.0, 10.0, 10.0, 70.0),  # left
        (90.0, 10.0, 90.0, 70.0),  # right
        (10.0, 70.0, 39.0, 70.0),  # bottom, left of the door
        (58.0, 70.0, 90.0, 70.0),  # bottom, right of the door
        (50.0, 10.0, 50.0, 40.0),  # inner wall, joined to the top one
    }


def turned_plan(angle_deg: float) -> tuple[npt.NDArray[np.int8], list[Float64Array]]:
    """Two rooms with two-cell walls, turned by ``angle_deg`` (cv2.warpAffine, nearest cell, as
    a map whose first pose was turned); and the turned centre lines of the walls, in cells."""
    cells = np.zeros((200, 240), dtype=np.uint8)
    centre_lines = [
        (20.5, 20.5, 219.5, 20.5), (20.5, 179.5, 219.5, 179.5), (20.5, 20.5, 20.5, 179.5),
        (219.5, 20.5, 219.5, 179.5), (120.5, 20.5, 120.5, 179.5),
    ]
    cells[20:22, 20:221] = cells[179:181, 20:221] = 1
    cells[20:181, 20:22] = cells[20:181, 219:221] = cells[20:181, 120:122] = 1
    turn = np.asarray(cv2.getRotationMatrix2D((120.0, 100.0), angle_deg, 1.0), dtype=np.float64)
    turn[:, 2] += 80.0  # room on the canvas for the turned corners
    turned = cv2.warpAffine(cells, turn, (400, 360), flags=cv2.INTER_NEAREST)
    grid = np.where(turned > 0, 100, 0).astype(np.int8)
    # Pixel centres: warpAffine maps pixel centres, the centre lines run between them (+0.5).
    truth = [
        np.concatenate([turn[:, :2] @ (np.array(p) - 0.5) + turn[:, 2] for p in (line[:2], line[2:])])
        for line in centre_lines
    ]
    return grid, truth


@pytest.mark.parametrize(("turn_deg", "margin"), [(20.0, 0), (37.0, 0), (20.0, 300)])
def test_walls_of_a_turned_map_are_found_at_their_angle_and_length(turn_deg: float, margin: int) -> None:
    plan, truth = turned_plan(turn_deg)
    # With a margin: the plan at (margin, 2 * margin) of a larger unknown map (only the part
    # holding walls is turned).
    cells = np.full((plan.shape[0] + 2 * margin, plan.shape[1] + 3 * margin), -1, dtype=np.int8)
    cells[margin : margin + plan.shape[0], 2 * margin : 2 * margin + plan.shape[1]] = plan
    truth = [t + np.array([2, 1, 2, 1]) * margin for t in truth]
    found = cell_segments(cells)
    assert found.shape == (5, 4)
    for expected in truth:
        best = min(found, key=lambda s: endpoint_error(s, expected))
        # Within two cells at both ends (the walls are two cells thick and resampled) ...
        assert endpoint_error(best, expected) <= 2.0
        length = np.hypot(*(best[2:] - best[:2]))
        assert length == pytest.approx(np.hypot(*(expected[2:] - expected[:2])), abs=3.0)
        # ... and at the angle they were turned to, within 0.6 degrees (the dominant direction is
        # estimated to a few tenths and rounded to ANGLE_STEP_DEG; the line fit levels what is
        # left when it rises less than a cell).
        difference = (angle_deg(best) - angle_deg(expected) + 90.0) % 180.0 - 90.0
        assert abs(difference) <= 0.6


def rooms(size: int) -> npt.NDArray[np.int8]:
    """Rooms on a 5 m pitch with two-cell walls and a door in every wall, as the benchmark's."""
    cells = np.zeros((size, size), dtype=np.int8)
    for at in range(10, size - 10, 100):
        cells[at : at + 2, 10 : size - 10] = 100
        cells[10 : size - 10, at : at + 2] = 100
        for door in range(at + 40, size - 30, 100):
            cells[at : at + 2, door : door + 18] = 0
            cells[door : door + 18, at : at + 2] = 0
    return cells


Tile = tuple[tuple[int, int], tuple[int, int]]


@pytest.fixture
def searched(monkeypatch: pytest.MonkeyPatch) -> list[Tile]:
    """The (rows, cols) of every tile the wall search looks at, in order."""
    from host_bridge.converters import segments

    found: list[Tile] = []
    search = segments._tile_findings

    def counted(mask: Any, rows: tuple[int, int], cols: tuple[int, int], min_run: int) -> Any:
        found.append((rows, cols))
        return search(mask, rows, cols, min_run)

    monkeypatch.setattr(segments, "_tile_findings", counted)
    return found


def test_tile_cache_searches_again_only_changed_tiles_and_matches_a_full_search(
    searched: list[Tile],
) -> None:
    from host_bridge.converters import segments

    options, cache = default_options(), segments.TileCache()
    cells = rooms(1100)  # 3 x 3 tiles of 512 cells
    walls.wall_segments(as_grid(cells), options, cache)
    # Nine tiles, each window searched once: two windows of this regular plan hold the same
    # cells at the same place in their tile, and share their findings.
    assert len(searched) == len(cache.tiles) == 8
    # A short wall in a room deep inside the middle tile: only that tile is searched again.
    searched.clear()
    changed = cells.copy()
    changed[700, 660:680] = 100
    cached = walls.wall_segments(as_grid(changed), options, cache)
    assert searched == [((512, 1024), (512, 1024))]
    np.testing.assert_array_equal(cached, walls.wall_segments(as_grid(changed), options))
    # A cell two cells from a tile edge is in the window of the neighbour tile too.
    searched.clear()
    changed[514, 700] = 100
    cached = walls.wall_segments(as_grid(changed), options, cache)
    assert sorted(searched) == [((0, 512), (512, 1024)), ((512, 1024), (512, 1024))]
    np.testing.assert_array_equal(cached, walls.wall_segments(as_grid(changed), options))


def test_a_grown_map_keeps_the_tiles_inside_the_old_one(searched: list[Tile]) -> None:
    # SLAM grows a map by whole cells and moves its origin: tiles stay on the same map cells,
    # so the tile that lay wholly inside the old map is not searched again.
    from host_bridge.converters import segments

    options, cache = default_options(), segments.TileCache()
    cells = rooms(1100)
    before = walls.wall_segments(as_grid(cells), options, cache)
    grown = np.full((1300, 1200), -1, dtype=np.int8)
    grown[200:, 100:] = cells  # 200 rows below the old map, 100 columns left of it
    message = grid_msg(grown, resolution=RES, origin=(-100 * RES, -200 * RES, 0.0))
    grid = occupancy.grid_from_msg(message, make_ctx("/map"))
    assert walls.tile_anchor(grid) == (-200, -100)
    searched.clear()
    after = walls.wall_segments(grid, options, cache)
    # Searched again: the tiles along the old map's bottom and left edges, whose windows
    # reached past them (now into unknown cells); not the middle one, nor those along the top
    # and right edges, which did not move.
    assert sorted(searched) == [
        ((200, 712), (100, 612)), ((200, 712), (612, 1124)), ((200, 712), (1124, 1200)),
        ((712, 1224), (100, 612)), ((1224, 1300), (100, 612)),
    ]
    np.testing.assert_allclose(after - np.array([100, 200, 100, 200]) * RES, before, atol=1e-9)


def test_walls_cover_the_wall_cells_as_the_canny_hough_detector_did() -> None:
    # The benchmark's plan (noise, doors, 37-degree walls), its first 1000 x 1000 cells. The
    # Canny + tiled Hough detector this one replaced found 192 walls there, covering 97.18 % of
    # the wall cells within a cell (the rest are noise specks).
    # By name: mypy checks benchmarks/ as scripts, and would see the module twice.
    benchmark = importlib.import_module("benchmarks.walls_4000")
    cells = benchmark.floor_plan(np.random.default_rng(7))[:1000, :1000].copy()
    found = np.round(walls.wall_segments(as_grid(cells), default_options()) / RES - 0.5).astype(int)
    wall = (cells >= 65) & (cells <= 100)
    near = np.zeros(cells.shape, dtype=np.uint8)
    for x0, y0, x1, y1 in found:
        cv2.line(near, (x0, y0), (x1, y1), 1, 3)
    assert (near[wall] > 0).mean() >= 0.9717
    assert 0.9 * 192 <= found.shape[0] <= 1.1 * 192


# Real maps: nav2's (tests/data/nav2_maps, its README says where from), read as map_server
# does (trinary). The Canny + tiled
# Hough detector this one replaced found these walls and covered these fractions of the wall
# cells within a cell (measured on the same maps, same default options).
NAV2_MAPS = Path(__file__).resolve().parents[2] / "data" / "nav2_maps"
CANNY_HOUGH = {
    "depot": (164, 0.9568), "tb3_sandbox": (58, 0.9747), "warehouse": (178, 0.9534), "map": (464, 0.7024),
}


def map_server_cells(pgm: Path) -> tuple[npt.NDArray[np.int8], float]:
    info = yaml.safe_load(pgm.with_suffix(".yaml").read_text())
    image = np.asarray(cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED), dtype=np.uint8)
    occupied = (255 - image.astype(np.float64)) / 255.0
    cells = np.full(image.shape, -1, dtype=np.int8)
    cells[occupied > info.get("occupied_thresh", 0.65)] = 100
    cells[occupied < info.get("free_thresh", 0.196)] = 0
    return np.ascontiguousarray(cells[::-1]), float(info["resolution"])  # image row 0 is the top


@pytest.mark.parametrize("name", sorted(CANNY_HOUGH))
def test_walls_of_real_maps_cover_their_wall_cells_as_before(name: str) -> None:
    pgm = NAV2_MAPS / f"{name}.png"
    cells, resolution = map_server_cells(pgm)
    grid = occupancy.grid_from_msg(grid_msg(cells, resolution=resolution), make_ctx("/map"))
    options = walls.WallOptions.from_options(GridOptions(), resolution, "/map")
    found = np.round(walls.wall_segments(grid, options) / resolution - 0.5).astype(int)
    near = np.zeros(cells.shape, dtype=np.uint8)
    for x0, y0, x1, y1 in found:
        cv2.line(near, (x0, y0), (x1, y1), 1, 3)
    count, coverage = CANNY_HOUGH[name]
    # Within a percentage point of the old coverage, and no more walls than it found (the
    # old one drew several crossing walls over every pillar).
    assert (near[cells == 100] > 0).mean() >= coverage - 0.01
    assert 0.6 * count <= found.shape[0] <= 1.1 * count
