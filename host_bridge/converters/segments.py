"""Wall segments from an occupancy grid: wall pixels -> axis runs + Hough -> merge -> corners -> boxes.

Pure numpy/OpenCV geometry with no ROS or Rerun types: :func:`occupied_mask` marks the wall
cells, :func:`detect_segments` finds wall pieces in pixels (runs along rows and columns, Hough
for the rest), :func:`merge_segments` folds the sides and fragments of one wall into its centre line,
:func:`join_corners` closes L corners and T junctions, and :func:`segments_to_mesh` extrudes the
result into boxes. ``converters/walls.py`` chains them for OccupancyGrid messages and holds the
options, their defaults and the reasoning behind them.
"""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

Float64Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class WallMesh:
    """Indexed triangles of the wall boxes: four vertices per face so every face shades flat."""

    vertices: npt.NDArray[np.float32]
    triangles: npt.NDArray[np.uint32]
    normals: npt.NDArray[np.float32]


# Maps are cut into TILE x TILE cells for the cache: small enough that a local change costs
# little, large enough that the per-tile Python and OpenCV calls stay a few milliseconds for a
# 4000x4000 map (64 tiles).
TILE = 512
# Residual pixels go to HoughLinesP in windows of this size (see :func:`_hough_pieces`).
HOUGH_TILE = 64
# A map whose walls are mostly not axis-aligned is searched again in the frame of its dominant
# wall direction, when that is further than this from the grid axes; below it the row and
# column runs of a wall are long and the line fit of their cluster follows the slope.
AXIS_TOLERANCE_DEG = 2.0
# The dominant direction is rounded to this step, so that a map changed in a few places turns
# the same way again and its unchanged tiles hit the cache; the remainder is left to the fit.
ANGLE_STEP_DEG = 0.25


def occupied_mask(cells: npt.NDArray[np.int8], occupied_threshold: int = 65) -> npt.NDArray[np.uint8]:
    """1 where a cell is a wall (value ``occupied_threshold``..100), else 0; rows in grid order.

    Row 0 stays row 0 (at the grid origin), so (col, row) is grid-local (x, y) in cells; -1
    (unknown) and values outside 0..100 are no wall.
    """
    import cv2

    lut = np.zeros(256, dtype=np.uint8)
    lut[occupied_threshold:101] = 1
    return np.asarray(cv2.LUT(np.ascontiguousarray(cells).view(np.uint8), lut), dtype=np.uint8)


@dataclass(frozen=True, slots=True)
class DetectorSettings:
    """Detection lengths in cells: ``min_run`` is the shortest axis run and Hough line, ``gap``
    the widest gap joined inside a run (the merge gap), ``fit_tolerance`` how far a run may lie
    from the line fitted through its cluster (half the merge distance: the two sides of one
    wall)."""

    min_run: int
    votes: int
    max_line_gap: float
    gap: int
    fit_tolerance: float


@dataclass(frozen=True, slots=True)
class TileFindings:
    """One tile's wall pixels, in cells from the tile's first row and column.

    ``along_rows``: runs (row, first col, last col) of wall pixels with a non-wall pixel above
    or below, part of a run at least ``min_run`` long; ``along_cols``: the same down columns,
    (col, first row, last row); ``rest``: (row, col) of the boundary wall pixels no such run
    holds (diagonal walls, clutter, noise).
    """

    along_rows: IntArray
    along_cols: IntArray
    rest: IntArray

    def shifted(self, row: int, col: int) -> TileFindings:
        return TileFindings(
            self.along_rows + np.array([row, col, col]),
            self.along_cols + np.array([col, row, row]),
            self.rest + np.array([row, col]),
        )


@dataclass(slots=True)
class TileCache:
    """Findings per tile, keyed by a digest of everything the tile's detection reads (its
    window of the mask with the halo, where the window sits, the settings, the frame); holds
    the tiles of the last map searched only, so it never outgrows one map."""

    tiles: dict[bytes, TileFindings] = field(default_factory=dict)


def _runs(mask: npt.NDArray[np.uint8]) -> IntArray:
    """Runs of 1s along each row: (row, first col, last col)."""
    import cv2

    padded = cv2.copyMakeBorder(mask, 0, 0, 1, 1, cv2.BORDER_CONSTANT, value=0)
    change = np.flatnonzero(padded[:, 1:] != padded[:, :-1])
    width = mask.shape[1] + 1
    starts, ends = change[0::2], change[1::2]
    return np.stack([starts // width, starts % width, ends % width - 1], axis=1).astype(np.int64)


def _run_pixels(runs: IntArray) -> IntArray:
    """Every pixel (line, position) of ``runs`` (line, first, last)."""
    lengths = runs[:, 2] - runs[:, 1] + 1
    owner = np.repeat(np.arange(runs.shape[0]), lengths)
    step = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    return np.stack([runs[owner, 0], runs[owner, 1] + step], axis=1)


def _in_runs(pixels: IntArray, runs: IntArray) -> npt.NDArray[np.bool_]:
    """Whether each pixel (line, position) lies in one of ``runs``, sorted by (line, first)."""
    if runs.shape[0] == 0:
        return np.zeros(pixels.shape[0], dtype=bool)
    stride = int(max(runs[:, 2].max(), pixels[:, 1].max(initial=0))) + 1
    at = np.searchsorted(runs[:, 0] * stride + runs[:, 1], pixels[:, 0] * stride + pixels[:, 1], "right") - 1
    run = runs[np.maximum(at, 0)]
    inside: npt.NDArray[np.bool_] = (at >= 0) & (run[:, 0] == pixels[:, 0]) & (run[:, 2] >= pixels[:, 1])
    return inside


def _clipped(runs: IntArray, lines: tuple[int, int], span: tuple[int, int]) -> IntArray:
    """``runs`` on lines [lines) cut to positions [span), both made relative to their starts."""
    runs = runs[(runs[:, 0] >= lines[0]) & (runs[:, 0] < lines[1])]
    first, last = np.maximum(runs[:, 1], span[0]), np.minimum(runs[:, 2], span[1] - 1)
    keep = first <= last
    return np.stack([runs[keep, 0] - lines[0], first[keep] - span[0], last[keep] - span[0]], axis=1)


def _tile_findings(
    mask: npt.NDArray[np.uint8], rows: tuple[int, int], cols: tuple[int, int], min_run: int
) -> TileFindings:
    """Axis runs and the rest of the wall pixels of mask[rows, cols] (tile-relative cells),
    read from a window reaching ``min_run`` + 1 cells further, so that how long a pixel's run
    is, and whether the pixel borders a non-wall pixel, is decided as on the whole mask."""
    import cv2

    reach = min_run + 1
    (top, bottom), (left, right) = rows, cols
    y0, x0 = max(top - reach, 0), max(left - reach, 0)
    y1, x1 = min(bottom + reach, mask.shape[0]), min(right + reach, mask.shape[1])
    window = np.asarray(
        cv2.copyMakeBorder(mask[y0:y1, x0:x1], 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0), np.uint8
    )
    wall = window[1:-1, 1:-1]
    # A wall pixel with wall above and below is inside a wall seen along the row (or a crossing
    # wall): only the two sides of a thick wall or blob make runs, as its two edges would.
    along_rows = _runs(wall & ~(window[:-2, 1:-1] & window[2:, 1:-1]))
    along_cols = _runs(np.asarray(cv2.transpose(wall & ~(window[1:-1, :-2] & window[1:-1, 2:])), np.uint8))
    long_rows = along_rows[along_rows[:, 2] - along_rows[:, 1] + 1 >= min_run]
    long_cols = along_cols[along_cols[:, 2] - along_cols[:, 1] + 1 >= min_run]
    # The rest: pixels of short runs in one direction that no long run holds in the other.
    short_rows = _run_pixels(along_rows[along_rows[:, 2] - along_rows[:, 1] + 1 < min_run])
    short_cols = _run_pixels(along_cols[along_cols[:, 2] - along_cols[:, 1] + 1 < min_run])
    rest = np.concatenate(
        [
            short_rows[~_in_runs(short_rows[:, ::-1], long_cols)],
            short_cols[~_in_runs(short_cols[:, ::-1], long_rows)][:, ::-1],
        ]
    )
    row_span, col_span = (top - y0, bottom - y0), (left - x0, right - x0)
    rest = rest[
        (rest[:, 0] >= row_span[0]) & (rest[:, 0] < row_span[1])
        & (rest[:, 1] >= col_span[0]) & (rest[:, 1] < col_span[1])
    ] - np.array([row_span[0], col_span[0]])
    # A pixel of short runs both ways is there twice.
    tile_width = right - left
    rest_key = np.unique(rest[:, 0] * tile_width + rest[:, 1])
    return TileFindings(
        _clipped(long_rows, row_span, col_span),
        _clipped(long_cols, col_span, row_span),
        np.stack([rest_key // tile_width, rest_key % tile_width], axis=1),
    )


def _tile_edges(size: int, offset: int) -> list[tuple[int, int]]:
    """[start, stop) of the tiles along one axis whose edges lie at k * TILE - offset."""
    edges = np.unique(np.clip(np.arange(-(offset % TILE), size + TILE, TILE), 0, size)).tolist()
    return list(itertools.pairwise(edges))


def _frame_findings(
    mask: npt.NDArray[np.uint8],
    *,
    anchor: tuple[int, int],
    min_run: int,
    frame: bytes,
    cache: TileCache,
    used: dict[bytes, TileFindings],
) -> TileFindings:
    """Findings of every tile of ``mask`` holding a wall pixel, from ``cache`` where a tile's
    window is unchanged; in mask cells. ``anchor`` (row, col) is the map cell of the mask's
    first cell, so tiles stay on the same map cells when the grid grows by whole cells."""
    reach = min_run + 1
    height, width = mask.shape
    parts = []
    for top, bottom in _tile_edges(height, anchor[0]):
        for left, right in _tile_edges(width, anchor[1]):
            y0, x0 = max(top - reach, 0), max(left - reach, 0)
            y1, x1 = min(bottom + reach, height), min(right + reach, width)
            window = mask[y0:y1, x0:x1]
            if not window.any():
                continue
            digest = hashlib.sha1(frame)
            placement = (top - y0, left - x0, bottom - top, right - left, y1 - y0, x1 - x0, min_run)
            digest.update(repr(placement).encode())
            digest.update(np.ascontiguousarray(window).data)
            key = digest.digest()
            found = used.get(key) or cache.tiles.get(key)
            if found is None:
                found = _tile_findings(mask, (top, bottom), (left, right), min_run)
            used[key] = found
            parts.append(found.shifted(top, left))
    if not parts:
        empty = np.zeros((0, 3), dtype=np.int64)
        return TileFindings(empty, empty, np.zeros((0, 2), dtype=np.int64))
    return TileFindings(
        np.concatenate([p.along_rows for p in parts]),
        np.concatenate([p.along_cols for p in parts]),
        np.concatenate([p.rest for p in parts]),
    )


def _joined(runs: IntArray, gap: int) -> IntArray:
    """Runs sorted by (line, first), runs on one line at most ``gap`` cells apart joined: the
    pieces of a run cut at tile edges, and the sides of a wall that a crossing wall, a speck
    next to it or a missing cell cut (a door is wider than the merge gap)."""
    runs = runs[np.lexsort((runs[:, 1], runs[:, 0]))]
    if runs.shape[0] == 0:
        return runs
    new = np.ones(runs.shape[0], dtype=bool)
    new[1:] = (runs[1:, 0] != runs[:-1, 0]) | (runs[1:, 1] > runs[:-1, 2] + 1 + gap)
    first = np.flatnonzero(new)
    last = np.append(first[1:], runs.shape[0]) - 1
    return np.stack([runs[first, 0], runs[first, 1], runs[last, 2]], axis=1)


def _components(count: int, a: npt.NDArray[np.intp], b: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """Connected component labels 0..k-1 of ``count`` nodes and edges (a, b): every node
    takes the lowest label of its neighbours and roots are hooked to it, with pointer jumping,
    until nothing changes."""
    label = np.arange(count)
    while True:
        low = np.minimum(label[a], label[b])
        new = label.copy()
        for side in (a, b):
            np.minimum.at(new, side, low)
            np.minimum.at(new, label[side], low)
        while True:
            jumped = new[new]
            if np.array_equal(jumped, new):
                break
            new = jumped
        if np.array_equal(new, label):
            break
        label = new
    return np.unique(label, return_inverse=True)[1]


def _run_clusters(runs: IntArray) -> npt.NDArray[np.intp]:
    """Cluster labels of runs sorted by (line, first): runs on neighbouring lines that overlap
    or touch at a corner (8-connected pixels) belong together, so the two sides of a wall and
    the steps of a slightly sloping wall are one cluster."""
    n = runs.shape[0]
    stride = int(runs[:, 2].max()) + 3
    line, first, last = runs[:, 0], runs[:, 1], runs[:, 2]
    start_key, end_key = line * stride + first, line * stride + last
    lo = np.searchsorted(end_key, (line + 1) * stride + first - 1, side="left")
    hi = np.searchsorted(start_key, (line + 1) * stride + last + 1, side="right")
    counts = np.maximum(hi - lo, 0)
    a = np.repeat(np.arange(n), counts)
    b = lo[a] + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    return _components(n, a, b)


def _fit_runs(runs: IntArray, settings: DetectorSettings) -> Float64Array:
    """One segment (along, line, along, line) per cluster of runs: the least-squares line of
    the cluster's pixels through their centroid, from the first to the last pixel projected
    on it. A cluster some run of which lies further than ``fit_tolerance`` from that line (a
    bend, a blob) gives its runs as they are, for the merge to sort out."""
    if runs.shape[0] == 0:
        return np.zeros((0, 4), dtype=np.float64)
    runs = _joined(runs, settings.gap)
    labels = _run_clusters(runs)
    count = int(labels.max()) + 1
    # Pixel moments per run about the first run of its cluster (small numbers, no cancellation).
    ref = runs[np.unique(labels, return_index=True)[1]].astype(np.float64)
    y = runs[:, 0] - ref[labels, 0]
    a = runs[:, 1] - ref[labels, 1]
    b = runs[:, 2] - ref[labels, 1]
    n = b - a + 1.0

    def square_sum(m: Float64Array) -> Float64Array:
        total: Float64Array = m * (m + 1.0) * (2.0 * m + 1.0) / 6.0
        return total

    sx, sxx = n * (a + b) / 2.0, square_sum(b) - square_sum(a - 1.0)
    sums = [np.bincount(labels, w, count) for w in (n, sx, n * y, sxx, n * y * y, y * sx)]
    total, mx, my = sums[0], sums[1] / sums[0], sums[2] / sums[0]
    cxx, cyy, cxy = sums[3] / total - mx * mx, sums[4] / total - my * my, sums[5] / total - mx * my
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    centre = np.stack([mx, my], axis=1)
    ends = [np.stack([a, y], axis=1) - centre[labels], np.stack([b, y], axis=1) - centre[labels]]

    def extent(angle: Float64Array) -> tuple[Float64Array, Float64Array, Float64Array]:
        """First and last run end along each cluster's line, and the furthest across it."""
        u = np.stack([np.cos(angle), np.sin(angle)], axis=1)[labels]
        along = [_dot(e, u) for e in ends]
        across = np.maximum(*(np.abs(e[:, 0] * u[:, 1] - e[:, 1] * u[:, 0]) for e in ends))
        t_min, t_max, worst = np.full(count, np.inf), np.full(count, -np.inf), np.zeros(count)
        np.minimum.at(t_min, labels, np.minimum(*along))
        np.maximum.at(t_max, labels, np.maximum(*along))
        np.maximum.at(worst, labels, across)
        return t_min, t_max, worst

    t_min, t_max, worst = extent(angle)
    # A line rising less than half a cell over its length is the axis: the slope of such a fit
    # comes from the two sides of a wall ending at different places (an L corner), not from
    # the wall.
    level = np.abs(np.sin(angle)) * (t_max - t_min) < 0.5
    if level.any():
        angle = np.where(level, 0.0, angle)
        t_min, t_max, worst = extent(angle)
    fits = worst <= settings.fit_tolerance
    u = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    centre += ref[:, [1, 0]]
    fitted = np.concatenate([centre + t_min[:, None] * u, centre + t_max[:, None] * u], axis=1)[fits]
    loose = runs[~fits[labels]].astype(np.float64)
    as_is = np.stack([loose[:, 1], loose[:, 0], loose[:, 2], loose[:, 0]], axis=1)
    return np.concatenate([fitted, as_is])


def _pixel_groups(pixels: IntArray) -> npt.NDArray[np.intp]:
    """The 8-connected group of each of the distinct (row, col) ``pixels``, -1 for a pixel
    without a neighbour among them (a speck, which can never make a wall)."""
    if pixels.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    stride = int(pixels[:, 1].max()) + 3
    key = (pixels[:, 0] + 1) * stride + pixels[:, 1] + 1
    order = np.argsort(key)
    ordered = key[order]
    firsts, seconds = [], []
    for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1)):
        probe = key + dy * stride + dx
        at = np.minimum(np.searchsorted(ordered, probe), key.size - 1)
        hit = ordered[at] == probe
        firsts.append(np.flatnonzero(hit))
        seconds.append(order[at[hit]])
    a, b = np.concatenate(firsts), np.concatenate(seconds)
    kept = np.zeros(key.size, dtype=bool)
    kept[a] = kept[b] = True
    index = np.cumsum(kept) - 1
    groups = np.full(key.size, -1, dtype=np.intp)
    groups[kept] = _components(int(kept.sum()), index[a], index[b])
    return groups


def _blob_segments(pixels: IntArray, labels: npt.NDArray[np.intp]) -> Float64Array:
    """Segments (x0, y0, x1, y1) for small groups of pixels (pillars, furniture legs, the bumps
    of a wall, short diagonal stubs), which hold too few pixels on one line for Hough: an
    elongated group (4:1) its least-squares line from end to end, any other the four sides of
    its bounding box."""
    count = int(labels.max(initial=-1)) + 1
    if count == 0:
        return np.zeros((0, 4), dtype=np.float64)
    y, x = pixels[:, 0].astype(np.float64), pixels[:, 1].astype(np.float64)
    low_x, low_y = np.full(count, np.inf), np.full(count, np.inf)
    high_x, high_y = np.full(count, -np.inf), np.full(count, -np.inf)
    for low, high, values in ((low_x, high_x, x), (low_y, high_y, y)):
        np.minimum.at(low, labels, values)
        np.maximum.at(high, labels, values)
    n = np.bincount(labels, minlength=count).astype(np.float64)
    mx, my = np.bincount(labels, x, count) / n, np.bincount(labels, y, count) / n
    cx, cy = x - mx[labels], y - my[labels]
    cxx, cyy, cxy = (np.bincount(labels, w, count) / n for w in (cx * cx, cy * cy, cx * cy))
    spread = np.sqrt((cxx - cyy) ** 2 + 4.0 * cxy * cxy)
    major, minor = (cxx + cyy + spread) / 2.0, (cxx + cyy - spread) / 2.0
    angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    ux, uy = np.cos(angle), np.sin(angle)
    t = cx * ux[labels] + cy * uy[labels]
    t_min, t_max = np.full(count, np.inf), np.full(count, -np.inf)
    np.minimum.at(t_min, labels, t)
    np.maximum.at(t_max, labels, t)
    line = major >= 16.0 * minor
    box = ~line
    # Box sides reach the outer edges of the end pixels (half a pixel past their centres), so a
    # pillar as long as the shortest wall keeps its sides.
    low_x, low_y, high_x, high_y = low_x - 0.5, low_y - 0.5, high_x + 0.5, high_y + 0.5
    sides = [
        np.stack([low_x, low_y + 0.5, high_x, low_y + 0.5], axis=1),
        np.stack([high_x - 0.5, low_y, high_x - 0.5, high_y], axis=1),
        np.stack([high_x, high_y - 0.5, low_x, high_y - 0.5], axis=1),
        np.stack([low_x + 0.5, high_y, low_x + 0.5, low_y], axis=1),
    ]
    lines = np.stack([mx + t_min * ux, my + t_min * uy, mx + t_max * ux, my + t_max * uy], axis=1)
    return np.concatenate([lines[line]] + [side[box] for side in sides])


def _small_groups(
    rest: IntArray, fitted: Float64Array, small: int
) -> tuple[IntArray, npt.NDArray[np.bool_], Float64Array]:
    """The pixels of ``rest`` Hough should search, which ``fitted`` segments stay, and the
    segments of the small groups of wall pixels drawn whole.

    A pillar, a furniture leg or the bump of a wall holds runs too short to be walls and too
    few pixels on one line for Hough. Groups of 8-connected rest pixels and pixels along the
    fitted runs shorter than ``small`` that fit in ``small`` x ``small`` cells become boxes or
    lines (:func:`_blob_segments`) instead; larger groups go to Hough whole, their short runs
    too; specks alone are dropped.
    """
    short = np.flatnonzero(np.hypot(fitted[:, 2] - fitted[:, 0], fitted[:, 3] - fitted[:, 1]) < small)
    steps = np.linspace(0.0, 1.0, small + 1)
    ends = fitted[short]
    along = ends[:, None, :2] + steps[None, :, None] * (ends[:, None, 2:] - ends[:, None, :2])
    run_pixels = np.round(along.reshape(-1, 2)[:, ::-1]).astype(np.int64)
    both = np.concatenate([rest, run_pixels])
    stride = int(both[:, 1].max(initial=0)) + 1
    keys, inverse = np.unique(both[:, 0] * stride + both[:, 1], return_inverse=True)
    pixels = np.stack([keys // stride, keys % stride], axis=1)
    groups = _pixel_groups(pixels)
    count = int(groups.max(initial=-1)) + 1
    grouped = groups >= 0
    low, high = np.full((count, 2), np.iinfo(np.int64).max), np.full((count, 2), -1)
    np.minimum.at(low, groups[grouped], pixels[grouped])
    np.maximum.at(high, groups[grouped], pixels[grouped])
    whole = np.zeros(count + 1, dtype=bool)  # index -1: specks, in no group
    whole[:count] = (high - low).max(axis=1, initial=0) < small
    in_blob = whole[groups]
    # A short run in a group is drawn by the group: a blob's box, or Hough with the group's
    # other pixels (the stair steps of a steep wall make short runs across it).
    stays = np.ones(fitted.shape[0], dtype=bool)
    stays[short[(groups[inverse[rest.shape[0] :]] >= 0).reshape(-1, small + 1).any(axis=1)]] = False
    blob_labels = np.unique(groups[in_blob], return_inverse=True)[1].reshape(-1)
    return pixels[grouped & ~in_blob], stays, _blob_segments(pixels[in_blob], blob_labels)


def _hough_pieces(pixels: IntArray, shape: tuple[int, ...], settings: DetectorSettings) -> Float64Array:
    """HoughLinesP over the HOUGH_TILE windows holding any of ``pixels`` (row, col) of an image
    of ``shape``; segments (x0, y0, x1, y1) in its pixels, at 1 px and 1 degree.

    Per window because the accumulator of a whole image collects votes from every wall on the
    same line of it (about a sixth of the walls of a floor plan went undetected).
    """
    import cv2

    if pixels.shape[0] < settings.votes:
        return np.zeros((0, 4), dtype=np.float64)
    margin = HOUGH_TILE // 4
    rows, cols = pixels[:, 0], pixels[:, 1]
    y_lo = max(int(rows.min()) // HOUGH_TILE * HOUGH_TILE - margin, 0)
    x_lo = max(int(cols.min()) // HOUGH_TILE * HOUGH_TILE - margin, 0)
    y_hi = min((int(rows.max()) // HOUGH_TILE + 1) * HOUGH_TILE + margin, shape[0])
    x_hi = min((int(cols.max()) // HOUGH_TILE + 1) * HOUGH_TILE + margin, shape[1])
    image = np.zeros((y_hi - y_lo, x_hi - x_lo), dtype=np.uint8)
    image[rows - y_lo, cols - x_lo] = 255
    # Windows overlap by a quarter tile on each side, so a wall ending just past a tile border
    # is still long enough to be found in the neighbouring window. A window holding fewer
    # pixels than the votes a line needs (specks, the stub a speck cuts off a wall) is skipped:
    # counts per quarter tile, summed over the 6x6 quarters of each window.
    quarters = np.zeros((-(-shape[0] // margin) + 2, -(-shape[1] // margin) + 2), dtype=np.int64)
    np.add.at(quarters, (rows // margin + 1, cols // margin + 1), 1)
    summed = np.pad(quarters.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    tile_index = np.unique((rows // HOUGH_TILE) * shape[1] + cols // HOUGH_TILE)
    tile_rows, tile_cols = np.divmod(tile_index, shape[1])
    q0r, q0c = tile_rows * 4, tile_cols * 4  # the window's first quarter, padded by one
    q1r, q1c = np.minimum(q0r + 6, quarters.shape[0]), np.minimum(q0c + 6, quarters.shape[1])
    in_window = summed[q1r, q1c] - summed[q0r, q1c] - summed[q1r, q0c] + summed[q0r, q0c]
    found: list[Float64Array] = []
    seen: list[Float64Array] = []
    busy = in_window >= settings.votes
    for tile_row, tile_col in zip(tile_rows[busy].tolist(), tile_cols[busy].tolist(), strict=True):
        y0, x0 = tile_row * HOUGH_TILE, tile_col * HOUGH_TILE
        y, x = max(y0 - margin, y_lo), max(x0 - margin, x_lo)
        window = image[y - y_lo : y0 + HOUGH_TILE + margin - y_lo, x - x_lo : x0 + HOUGH_TILE + margin - x_lo]
        lines = cv2.HoughLinesP(
            window,
            1.0,
            math.pi / 180.0,
            settings.votes,
            minLineLength=float(settings.min_run),
            maxLineGap=settings.max_line_gap,
        )
        if lines is not None:
            window_rows, window_cols = np.nonzero(window)
            found.append(np.asarray(lines, dtype=np.float64).reshape(-1, 4) + np.array([x, y, x, y]))
            seen.append(np.stack([window_cols + x, window_rows + y], axis=1).astype(np.float64))
    # Each line is refitted to the pixels of its window, windows of similar pixel counts padded
    # to one array per call, a few million (line, pixel) pairs at most.
    refitted = [np.zeros((0, 4), dtype=np.float64)]
    block: list[int] = []
    for index in sorted(range(len(found)), key=lambda i: len(seen[i])):
        block.append(index)
        if sum(len(found[i]) for i in block) * len(seen[index]) > 2_000_000:
            refitted.append(_refitted_windows([found[i] for i in block], [seen[i] for i in block], settings))
            block = []
    if block:
        refitted.append(_refitted_windows([found[i] for i in block], [seen[i] for i in block], settings))
    return np.concatenate(refitted)


def _refitted_windows(
    lines: list[Float64Array], pixels: list[Float64Array], settings: DetectorSettings
) -> Float64Array:
    """:func:`_refitted` for the lines of several windows, each window's pixels padded."""
    window_of = np.repeat(np.arange(len(lines)), [len(f) for f in lines])
    most = max(len(p) for p in pixels)
    pixels_of = np.zeros((len(pixels), most, 2))
    valid = np.zeros((len(pixels), most), dtype=bool)
    for index, window_pixels in enumerate(pixels):
        pixels_of[index, : len(window_pixels)] = window_pixels
        valid[index, : len(window_pixels)] = True
    return _refitted(np.concatenate(lines), pixels_of[window_of], valid[window_of], settings.max_line_gap)


def _refitted(
    lines: Float64Array, pixels: Float64Array, valid: npt.NDArray[np.bool_], max_gap: float
) -> Float64Array:
    """Hough lines (k, 4) refitted to the pixels (x, y) they stand for, each from its own
    pixels (k, m, 2) where ``valid``: those within 1.5 px of a line and at most ``max_gap`` + 2
    px past its ends; their least-squares line, from the first to the last of them; three
    times, each along the fit before. HoughLinesP walks along its 1-degree angle and leaves a
    long one-cell diagonal early, where that drifts a pixel off it; each round reaches a few
    pixels further along the wall."""
    segment = lines
    reach = max_gap + 2.0
    px, py = pixels[:, :, 0], pixels[:, :, 1]
    for _ in range(3):
        start = segment[:, :2]
        length = np.hypot(segment[:, 2] - segment[:, 0], segment[:, 3] - segment[:, 1])
        u = (segment[:, 2:] - start) / np.maximum(length, 1e-9)[:, None]
        dx, dy = px - start[:, 0, None], py - start[:, 1, None]
        along = dx * u[:, 0, None] + dy * u[:, 1, None]
        member = (
            valid
            & (np.abs(dy * u[:, 0, None] - dx * u[:, 1, None]) <= 1.5)
            & (along >= -reach)
            & (along <= length[:, None] + reach)
        )
        count = member.sum(axis=1)
        weight = member / np.maximum(count, 1)[:, None]
        mx, my = (weight * px).sum(1), (weight * py).sum(1)
        cx, cy = px - mx[:, None], py - my[:, None]
        cxx, cyy, cxy = (weight * cx * cx).sum(1), (weight * cy * cy).sum(1), (weight * cx * cy).sum(1)
        angle = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
        ax, ay = np.cos(angle), np.sin(angle)
        t = cx * ax[:, None] + cy * ay[:, None]
        t_min = np.where(member, t, np.inf).min(axis=1)
        t_max = np.where(member, t, -np.inf).max(axis=1)
        with np.errstate(invalid="ignore"):  # lines without pixels, kept as they are below
            refit = np.stack([mx + t_min * ax, my + t_min * ay, mx + t_max * ax, my + t_max * ay], axis=1)
        segment = np.where((count >= 2)[:, None], refit, segment)
    return segment


@dataclass(frozen=True, slots=True)
class _FrameFindings:
    """What the runs of a frame (the mask, or the mask turned) explain: segments fitted to them,
    and the boundary pixels they leave."""

    segments: Float64Array
    rest: IntArray  # (row, col)
    aligned: float  # length of the walls fitted to runs within AXIS_TOLERANCE_DEG of an axis
    other: float  # length of the other fitted walls, and the pixels no run holds


def _frame_segments(
    mask: npt.NDArray[np.uint8],
    settings: DetectorSettings,
    *,
    anchor: tuple[int, int],
    frame: bytes,
    cache: TileCache,
    used: dict[bytes, TileFindings],
) -> _FrameFindings:
    found = _frame_findings(
        mask, anchor=anchor, min_run=settings.min_run, frame=frame, cache=cache, used=used
    )
    fitted = np.concatenate(
        [_fit_runs(found.along_rows, settings), _fit_runs(found.along_cols, settings)[:, [1, 0, 3, 2]]]
    )
    delta = fitted[:, 2:] - fitted[:, :2]
    length = np.hypot(delta[:, 0], delta[:, 1])
    direction = np.degrees(np.arctan2(delta[:, 1], delta[:, 0]))
    off_axis = np.abs(direction % 90.0 - 45.0) < 45.0 - AXIS_TOLERANCE_DEG
    aligned, other = float(length[~off_axis].sum()), float(length[off_axis].sum()) + found.rest.shape[0]
    return _FrameFindings(fitted, found.rest, aligned, other)


def _frame_pieces(found: _FrameFindings, shape: tuple[int, ...], settings: DetectorSettings) -> Float64Array:
    """All pieces of the frame searched: the fitted runs, the small groups, Hough's lines."""
    rest, stays, blobs = _small_groups(found.rest, found.segments, 4 * settings.min_run)
    return np.concatenate([found.segments[stays], blobs, _hough_pieces(rest, shape, settings)])


def dominant_angle_deg(mask: npt.NDArray[np.uint8]) -> float:
    """Direction of most wall edges modulo 90 degrees, in [-45, 45).

    Edge directions come from the structure tensor (gradient products averaged over 9x9
    cells): single gradients of a turned, one-cell wall point along its stair steps, their
    average across the steps along the wall. The peak of a histogram of these directions
    (weighted by edge strength, half-degree bins, on the circle of 4x the angle where the four
    directions of a rectangular building coincide) is refined by the mean within 5 degrees.
    """
    import cv2

    # Directions do not need every cell: a mask larger than about a megapixel is averaged down.
    shrink = max(1, math.ceil(math.sqrt(mask.size / 1e6)))
    image = mask * np.uint8(255)
    if shrink > 1:
        size = (max(mask.shape[1] // shrink, 1), max(mask.shape[0] // shrink, 1))
        image = np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    blurred = cv2.GaussianBlur(image.astype(np.float32) / 255.0, (9, 9), 0)
    dx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3)
    dy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)
    jxx, jyy, jxy = (cv2.boxFilter(p, -1, (9, 9)) for p in (dx * dx, dy * dy, dx * dy))
    strength = cv2.sqrt((jxx - jyy) ** 2 + 4.0 * jxy * jxy)
    edge = strength > 0.1 * float(strength.max(initial=0.0))
    if not edge.any():
        return 0.0
    weight = strength[edge].astype(np.float64)
    quarter = 2.0 * np.arctan2(2.0 * jxy[edge], (jxx - jyy)[edge]).astype(np.float64)
    histogram = np.bincount((np.degrees(quarter) % 360.0 / 2.0).astype(np.intp) % 180, weight, 180)
    smooth = histogram + np.roll(histogram, 1) + np.roll(histogram, -1)
    peak = math.radians((int(np.argmax(smooth)) + 0.5) * 2.0)
    near = np.abs(np.angle(np.exp(1j * (quarter - peak)))) < math.radians(20.0)
    mean = np.angle(np.sum(weight[near] * np.exp(1j * quarter[near]))) / 4.0
    return (math.degrees(mean) + 45.0) % 90.0 - 45.0


def _turned(mask: npt.NDArray[np.uint8], angle_deg: float) -> tuple[npt.NDArray[np.uint8], Float64Array]:
    """``mask`` turned so that directions at ``angle_deg`` run along the rows, on a canvas
    holding all of it; and the affine map from the turned pixels back to the mask's."""
    import cv2

    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    turn = np.array([[c, s], [-s, c]])
    height, width = mask.shape
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]]) @ turn.T
    low = corners.min(axis=0) - 2.0
    size = np.ceil(corners.max(axis=0) - low + 3.0).astype(int)
    forward = np.concatenate([turn, -low[:, None]], axis=1)
    # Bilinear and a low threshold: a one-cell wall stays connected when turned.
    turned = cv2.warpAffine(
        mask * np.uint8(255), forward, (int(size[0]), int(size[1])), flags=cv2.INTER_LINEAR
    )
    back = np.asarray(cv2.invertAffineTransform(forward), dtype=np.float64)
    # Closing fills the one-cell notches resampling leaves along the sides of a wall, which
    # would cut its runs into pieces too short to keep.
    closed = cv2.morphologyEx((turned >= 64).view(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    return np.asarray(closed, dtype=np.uint8), back


def detect_segments(
    mask: npt.NDArray[np.uint8],
    settings: DetectorSettings,
    *,
    anchor: tuple[int, int] = (0, 0),
    cache: TileCache | None = None,
) -> Float64Array:
    """Wall pieces (x0, y0, x1, y1) in pixels of a wall ``mask`` (:func:`occupied_mask`),
    shape (N, 4), for :func:`merge_segments`.

    Axis-aligned walls (most walls of a building map) are runs of boundary wall pixels along
    rows and columns, found with a few whole-array operations per tile; the runs of one wall
    (its two sides, the steps of a slight slope) are clustered and fitted with one line.
    What no run explains (diagonal walls) goes to HoughLinesP, in the windows holding it only.
    When most of what was found is off the axes (walls fitted more than AXIS_TOLERANCE_DEG
    off them, pixels no run holds) and so is the map's dominant direction (a SLAM map whose
    first pose was turned), the map is searched again turned into that direction, and the
    pieces turned back: runs break up on walls turned much more than a few degrees.

    ``cache`` keeps each tile's findings between calls (see :class:`TileCache`): a map that
    changed in a few places is searched again only where its tiles' windows changed.
    """
    import cv2

    cache = TileCache() if cache is None else cache
    used: dict[bytes, TileFindings] = {}
    found = _frame_segments(mask, settings, anchor=anchor, frame=b"axes", cache=cache, used=used)
    angle = 0.0
    # Turned, only the part holding walls (a SLAM map is mostly unknown margin).
    x, y, width, height = cv2.boundingRect(mask)
    walled = mask[y : y + height, x : x + width]
    if found.other > found.aligned:
        angle = round(dominant_angle_deg(walled) / ANGLE_STEP_DEG) * ANGLE_STEP_DEG
    if abs(angle) <= AXIS_TOLERANCE_DEG:
        cache.tiles = used
        return _frame_pieces(found, mask.shape, settings)
    turned, back = _turned(walled, angle)
    found = _frame_segments(
        turned, settings, anchor=(0, 0), frame=f"turned {angle}".encode(), cache=cache, used=used
    )
    cache.tiles = used
    ends = _rotated(_frame_pieces(found, turned.shape, settings).reshape(-1, 2), back[:, :2]) + back[:, 2]
    pieces: Float64Array = ends.reshape(-1, 4) + np.array([x, y, x, y])
    return pieces


def _canonical(segments: Float64Array) -> Float64Array:
    """Endpoints ordered along +x (then +y), rows sorted: the merge sees one order for any input."""
    swap = (segments[:, 2] < segments[:, 0]) | (
        (segments[:, 2] == segments[:, 0]) & (segments[:, 3] < segments[:, 1])
    )
    out = np.where(swap[:, None], segments[:, [2, 3, 0, 1]], segments)
    return out[np.lexsort((out[:, 3], out[:, 2], out[:, 1], out[:, 0]))]


@dataclass(frozen=True, slots=True)
class _Geometry:
    """Per-segment quantities; ``doubled`` is (cos 2a, sin 2a): a direction modulo pi."""

    p0: Float64Array
    p1: Float64Array
    length: Float64Array
    mid: Float64Array
    doubled: Float64Array

    @classmethod
    def of(cls, segments: Float64Array) -> _Geometry:
        p0, p1 = segments[:, :2], segments[:, 2:]
        d = p1 - p0
        length = np.hypot(d[:, 0], d[:, 1])
        doubled = np.stack([d[:, 0] ** 2 - d[:, 1] ** 2, 2.0 * d[:, 0] * d[:, 1]], axis=1)
        return cls(p0, p1, length, (p0 + p1) / 2.0, doubled / (length**2)[:, None])

    def directions(self) -> Float64Array:
        return (self.p1 - self.p0) / self.length[:, None]

    def normals(self) -> Float64Array:
        u = self.directions()
        return np.stack([-u[:, 1], u[:, 0]], axis=1)


def _directions(doubled_sum: Float64Array) -> Float64Array:
    """Unit directions of mean angles modulo pi (half the angle of a doubled-angle sum)."""
    half = 0.5 * np.arctan2(doubled_sum[:, 1], doubled_sum[:, 0])
    directions: Float64Array = np.stack([np.cos(half), np.sin(half)], axis=1)
    return directions


def _dot(a: Float64Array, b: Float64Array) -> Float64Array:
    rowwise: Float64Array = np.einsum("ij,ij->i", a, b)
    return rowwise


def _runs_pairs(group: npt.NDArray[np.intp]) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """All index pairs (a < b) of positions with equal ``group`` values; ``group`` is sorted."""
    end = np.searchsorted(group, group, side="right")
    counts = end - np.arange(1, group.size + 1)
    first = np.repeat(np.arange(group.size), counts)
    offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    return first, first + 1 + offset


def _candidate_pairs(
    g: _Geometry, reach: float, sin_angle: float
) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Pairs whose bounding boxes, grown by what a mergeable pair can be apart, overlap.

    Two mergeable segments have points closer than gap + distance + (L_i + L_j)/2 * sin(angle)
    (their directions are within the angle of the shared direction), so growing each box by
    half the constant plus L/2 * sin(angle) loses no pair. Boxes are hashed into square cells
    of the median box size; only boxes sharing a cell are compared (a sweep along one axis
    compared every wall of a floor plan with all walls of the same rows or columns).
    """
    n = g.length.size
    if n < 2:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    grow = reach / 2.0 + g.length * sin_angle / 2.0
    lo = np.minimum(g.p0, g.p1) - grow[:, None]
    hi = np.maximum(g.p0, g.p1) + grow[:, None]
    size = float(np.median((hi - lo).max(axis=1)))
    cell_lo = np.floor(lo / size).astype(np.int64)
    spans = np.floor(hi / size).astype(np.int64) - cell_lo + 1
    per_box = spans[:, 0] * spans[:, 1]
    owner = np.repeat(np.arange(n), per_box)
    k = np.arange(per_box.sum()) - np.repeat(np.cumsum(per_box) - per_box, per_box)
    cx = cell_lo[owner, 0] + k % spans[owner, 0]
    cy = cell_lo[owner, 1] + k // spans[owner, 0]
    order = np.lexsort((owner, cy, cx))
    cx, cy, owner = cx[order], cy[order], owner[order]
    cell = np.cumsum(np.concatenate([[0], (cx[1:] != cx[:-1]) | (cy[1:] != cy[:-1])]))
    a, b = _runs_pairs(cell)
    i, j = owner[a], owner[b]
    # Overlapping boxes share every cell over their overlap; keep the pair only in the cell
    # holding the overlap's low corner, so each pair comes out once.
    corner = np.floor(np.maximum(lo[i], lo[j]) / size).astype(np.int64)
    keep = (
        (lo[i] <= hi[j]).all(axis=1)
        & (lo[j] <= hi[i]).all(axis=1)
        & (corner[:, 0] == cx[a])
        & (corner[:, 1] == cy[a])
    )
    return i[keep], j[keep]


def _best_partners(
    segments: Float64Array, angle_rad: float, distance: float, gap: float
) -> npt.NDArray[np.intp]:
    """Index of each segment's closest mergeable partner, -1 for none.

    Closest means the smallest perpendicular distance plus gap; ties go to the lower index,
    which rules out cycles longer than two: following ``best`` always ends in a mutual pair.
    """
    g = _Geometry.of(segments)
    i, j = _candidate_pairs(g, distance + gap, math.sin(angle_rad))
    cos_doubled = _dot(g.doubled[i], g.doubled[j])
    u = _directions(g.doubled[i] * g.length[i, None] + g.doubled[j] * g.length[j, None])
    normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
    perpendicular = np.abs(_dot(normal, g.mid[i] - g.mid[j]))
    ti = np.stack([_dot(u, g.p0[i]), _dot(u, g.p1[i])])
    tj = np.stack([_dot(u, g.p0[j]), _dot(u, g.p1[j])])
    along_gap = np.maximum(ti.min(0), tj.min(0)) - np.minimum(ti.max(0), tj.max(0))
    ok = (cos_doubled > math.cos(2.0 * angle_rad)) & (perpendicular < distance) & (along_gap < gap)
    best = np.full(segments.shape[0], -1, dtype=np.intp)
    score = perpendicular[ok] + np.maximum(along_gap[ok], 0.0)
    a = np.concatenate([i[ok], j[ok]])
    b = np.concatenate([j[ok], i[ok]])
    order = np.lexsort((b, np.concatenate([score, score]), a))
    a, b = a[order], b[order]
    first = np.ones(a.size, dtype=bool)
    first[1:] = a[1:] != a[:-1]
    best[a[first]] = b[first]
    return best


def _cluster_segments(
    segments: Float64Array, labels: npt.NDArray[np.intp], count: int
) -> Float64Array:
    """One segment per cluster: every member endpoint projected on the length-weighted mean
    direction through the length-weighted centroid, extremes kept; singletons unchanged."""
    g = _Geometry.of(segments)
    weight = np.bincount(labels, g.length, count)
    u = _directions(
        np.stack(
            [np.bincount(labels, g.doubled[:, k] * g.length, count) for k in range(2)], axis=1
        )
    )
    centroid = np.stack(
        [np.bincount(labels, g.mid[:, k] * g.length, count) for k in range(2)], axis=1
    ) / weight[:, None]
    t0 = _dot(g.p0 - centroid[labels], u[labels])
    t1 = _dot(g.p1 - centroid[labels], u[labels])
    t_min = np.full(count, np.inf)
    t_max = np.full(count, -np.inf)
    np.minimum.at(t_min, labels, np.minimum(t0, t1))
    np.maximum.at(t_max, labels, np.maximum(t0, t1))
    out = np.concatenate([centroid + t_min[:, None] * u, centroid + t_max[:, None] * u], axis=1)
    alone = np.flatnonzero(np.bincount(labels, minlength=count)[labels] == 1)
    out[labels[alone]] = segments[alone]
    return out


def _merge_targets(
    segments: Float64Array,
    *,
    labels: npt.NDArray[np.intp],
    current: Float64Array,
    best: npt.NDArray[np.intp],
    angle_rad: float,
    distance: float,
) -> npt.NDArray[np.intp]:
    """The cluster each current cluster joins this round (itself when it stays).

    Following ``best`` groups clusters into trees rooted in a mutual pair; a whole tree merges
    at once (a long wall absorbs all its fragments in one round, not one per round) when every
    member lies within ``distance / 2`` and the angle of the tree's merged line, as the two
    edges of one wall do around its centre. A tree that fails, e.g. one reaching across to a
    parallel wall, merges only its mutual pair, and the merged line is re-tested next round.
    """
    index = np.arange(current.shape[0])
    mutual_low = (best > index) & (best[np.maximum(best, 0)] == index)
    pair_target = index.copy()
    pair_target[best[mutual_low]] = index[mutual_low]
    root = np.where(best >= 0, best, index)
    root[mutual_low] = index[mutual_low]
    while True:
        jumped = root[root]
        if np.array_equal(jumped, root):
            break
        root = jumped
    roots, tree_labels = np.unique(root[labels], return_inverse=True)
    tree = _Geometry.of(_cluster_segments(segments, tree_labels, roots.size))
    member = _Geometry.of(current)
    of_tree = np.searchsorted(roots, root)
    fits = (
        np.abs(_dot(tree.normals()[of_tree], member.mid - tree.mid[of_tree])) < distance / 2.0
    ) & (_dot(member.doubled, tree.doubled[of_tree]) > math.cos(2.0 * angle_rad))
    misfits = np.bincount(of_tree, ~fits, roots.size) > 0
    return np.where(misfits[of_tree], pair_target, root)


def merge_segments(
    segments: npt.ArrayLike,
    *,
    angle_deg: float,
    distance: float,
    gap: float,
    min_length: float = 0.0,
) -> Float64Array:
    """Merge collinear, close segments until nothing merges; (M, 4), canonical order.

    Mergeable: directions (modulo pi) differ by less than ``angle_deg``, the midpoints are less
    than ``distance`` apart across the pair's shared direction, and the extents along it overlap
    or leave a gap below ``gap``. Clusters are re-formed from the original segments each round,
    so a merged wall is always the projection of all its pieces. The result does not depend on
    the input order and merging it again returns it unchanged. Units are the caller's.
    """
    segs = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    segs = _canonical(segs[np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]) > 0.0])
    angle_rad = math.radians(angle_deg)
    labels = np.arange(segs.shape[0])
    current = segs
    while current.shape[0] > 1:
        best = _best_partners(current, angle_rad, distance, gap)
        if (best < 0).all():
            break
        target = _merge_targets(
            segs, labels=labels, current=current, best=best, angle_rad=angle_rad, distance=distance
        )
        kept, labels = np.unique(target[labels], return_inverse=True)
        current = _cluster_segments(segs, labels, kept.size)
    out = _canonical(current)
    return out[np.hypot(out[:, 2] - out[:, 0], out[:, 3] - out[:, 1]) >= min_length]


def _cross(a: Float64Array, b: Float64Array) -> Float64Array:
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def join_corners(segments: npt.ArrayLike, *, reach: float, min_angle_deg: float = 30.0) -> Float64Array:
    """Move wall ends near a crossing wall onto that wall's centre line.

    The sides of a wall stop at the side of the wall they run into, and the outer side of an L
    corner runs on to the corner's outer edge, so after merging, the walls of an L corner or a
    T junction end up to a few cells short of each other's centre lines, or half a wall past.
    An end moves to where its line meets the line of a segment at least ``min_angle_deg`` away
    in direction, when that point is on the other segment or within ``reach`` of it, and at
    most ``reach`` beyond the end or ``reach / 2`` (and a quarter of the segment) back from
    it; the nearest such point wins. Segments crossing further inside are left alone.
    """
    segs = np.array(segments, dtype=np.float64).reshape(-1, 4)
    g = _Geometry.of(segs)
    i, j = _candidate_pairs(g, 2.0 * reach, 0.0)
    a, b = np.concatenate([i, j]), np.concatenate([j, i])
    u = g.directions()
    sine = _cross(u[a], u[b])
    steep = np.abs(sine) > math.sin(math.radians(min_angle_deg))
    a, b, sine = a[steep], b[steep], sine[steep]
    offset = g.p0[b] - g.p0[a]
    t = _cross(offset, u[b]) / sine
    s = _cross(offset, u[a]) / sine
    on_b = (s >= -reach) & (s <= g.length[b] + reach)
    back = np.minimum(reach / 2.0, g.length[a] / 4.0)
    near_start = on_b & (t >= -reach) & (t <= back)
    near_end = on_b & (t >= g.length[a] - back) & (t <= g.length[a] + reach)
    seg = np.concatenate([a[near_start], a[near_end]])
    end = np.concatenate([np.zeros(near_start.sum(), np.intp), np.ones(near_end.sum(), np.intp)])
    t_end = np.concatenate([t[near_start], t[near_end]])
    extension = np.abs(np.concatenate([t[near_start], t[near_end] - g.length[a[near_end]]]))
    order = np.lexsort((extension, end, seg))
    seg, end, t_end = seg[order], end[order], t_end[order]
    first = np.ones(seg.size, dtype=bool)
    first[1:] = (seg[1:] != seg[:-1]) | (end[1:] != end[:-1])
    seg, end, t_end = seg[first], end[first], t_end[first]
    points = g.p0[seg] + t_end[:, None] * u[seg]
    segs[seg[end == 0], :2] = points[end == 0]
    segs[seg[end == 1], 2:] = points[end == 1]
    return segs


def _rotated(points: Float64Array, rotation: Float64Array) -> Float64Array:
    """``points @ rotation.T`` without BLAS: a matrix product with an inner size of 3 starts
    OpenBLAS's threads, which on a busy 2-core machine made a 3000-box mesh take 5 to 100 ms."""
    turned = points[:, 0, None] * rotation[:, 0]
    for k in range(1, points.shape[1]):
        turned = turned + points[:, k, None] * rotation[:, k]
    return turned


def _rotation(quaternion_xyzw: Float64Array) -> Float64Array:
    x, y, z, w = quaternion_xyzw / np.linalg.norm(quaternion_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


# Box corners 0-3 at z=0 (p0-n, p1-n, p1+n, p0+n), 4-7 the same at the top; each face lists
# its corners counter-clockwise seen from outside. Faces: bottom, top, -n, +n, p0 end, p1 end.
_FACES = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [3, 0, 4, 7], [1, 2, 6, 5]]
)
_QUAD_TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]])


def segments_to_mesh(
    segments_m: npt.ArrayLike,
    translation: npt.ArrayLike,
    quaternion_xyzw: npt.ArrayLike,
    height: float,
    thickness: float,
) -> WallMesh:
    """Boxes over grid-local segments (metres), placed with the grid origin pose.

    Each box reaches half its thickness past both ends of its segment, so two walls joined at
    a corner point (see :func:`join_corners`) close the corner instead of leaving a notch.
    """
    g = _Geometry.of(np.asarray(segments_m, dtype=np.float64).reshape(-1, 4))
    n_boxes = g.length.size
    u, n = g.directions(), g.normals()
    p0 = g.p0 - u * (thickness / 2.0)
    p1 = g.p1 + u * (thickness / 2.0)
    side = n * (thickness / 2.0)
    footprint = np.stack([p0 - side, p1 - side, p1 + side, p0 + side], axis=1)
    corners = np.zeros((n_boxes, 8, 3))
    corners[:, :4, :2] = footprint
    corners[:, 4:, :2] = footprint
    corners[:, 4:, 2] = height
    zeros, ones = np.zeros(n_boxes), np.ones(n_boxes)
    u3 = np.stack([u[:, 0], u[:, 1], zeros], axis=1)
    n3 = np.stack([n[:, 0], n[:, 1], zeros], axis=1)
    z3 = np.stack([zeros, zeros, ones], axis=1)
    face_normals = np.stack([-z3, z3, -n3, n3, -u3, u3], axis=1)
    rotation = _rotation(np.asarray(quaternion_xyzw, dtype=np.float64))
    local = corners[:, _FACES].reshape(-1, 3)
    vertices = _rotated(local, rotation) + np.asarray(translation, dtype=np.float64)
    normals = _rotated(np.repeat(face_normals, 4, axis=1).reshape(-1, 3), rotation)
    quad_starts = np.arange(n_boxes * 6) * 4
    triangles = (quad_starts[:, None, None] + _QUAD_TRIANGLES[None]).reshape(-1, 3)
    return WallMesh(
        vertices.astype(np.float32), triangles.astype(np.uint32), normals.astype(np.float32)
    )
