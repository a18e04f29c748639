"""Wall segments from an occupancy image: pixels -> Canny + HoughLinesP -> merge -> corners -> boxes.

Pure numpy/OpenCV geometry with no ROS or Rerun types: :func:`grid_to_image` turns occupancy
values into intensities an edge detector separates, :func:`detect_segments` finds edge segments
in pixels, :func:`merge_segments` folds the edges and fragments of one wall into its centre line,
:func:`join_corners` closes L corners and T junctions, and :func:`segments_to_mesh` extrudes the
result into boxes. ``converters/walls.py`` chains them for OccupancyGrid messages and holds the
options, their defaults and the reasoning behind them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Float64Array = npt.NDArray[np.float64]

# Image intensities: unknown sits close to free so that a frontier (free next to unknown) stays
# below Canny's low threshold while walls next to either are strong edges. After the 3x3 blur
# (measured, L2 Sobel): frontiers <= ~100, an isolated occupied cell ~190 (a weak edge, dropped
# unless it touches a wall), a one-cell wall >= ~280 at any angle, next to free or unknown.
FREE, UNKNOWN, OCCUPIED = 0, 32, 255

@dataclass(frozen=True, slots=True)
class WallMesh:
    """Indexed triangles of the wall boxes: four vertices per face so every face shades flat."""

    vertices: npt.NDArray[np.float32]
    triangles: npt.NDArray[np.uint32]
    normals: npt.NDArray[np.float32]


def grid_to_image(cells: npt.NDArray[np.int8], occupied_threshold: int = 65) -> npt.NDArray[np.uint8]:
    """Occupancy values -> FREE / UNKNOWN / OCCUPIED intensities, rows in grid order.

    Row 0 stays row 0 (at the grid origin), so image (col, row) is grid-local (x, y) in cells;
    values outside 0..100 (-1 and anything invalid) count as unknown.
    """
    import cv2

    lut = np.full(256, UNKNOWN, dtype=np.uint8)
    lut[:occupied_threshold] = FREE
    lut[occupied_threshold:101] = OCCUPIED
    return np.asarray(cv2.LUT(np.ascontiguousarray(cells).view(np.uint8), lut), dtype=np.uint8)


def _tiled_hough(
    part_shape: tuple[int, ...],
    *,
    rows: npt.NDArray[np.intp],
    cols: npt.NDArray[np.intp],
    origin: tuple[int, int],
    shape: tuple[int, ...],
    votes: int,
    min_line_length: float,
    max_line_gap: float,
    tile: int,
) -> Float64Array:
    """HoughLinesP over the windows holding any of the edge pixels (rows, cols) of a part of
    an image of ``shape``, the part starting at ``origin`` (row, col); segments in the image's
    pixels. Tiles and windows are those of the whole image, so a part holding every window
    that has an edge pixel finds exactly what the whole image would.
    """
    import cv2

    edges = np.zeros(part_shape, dtype=np.uint8)
    edges[rows, cols] = 255
    rows_at, cols_at = origin
    tiles_x = -(-shape[1] // tile)
    occupied = np.unique(((rows + rows_at) // tile) * tiles_x + (cols + cols_at) // tile)
    # Windows overlap by a quarter tile on each side, so a wall ending just past a tile border
    # is still long enough to be found in the neighbouring window.
    margin = tile // 4
    found = [np.zeros((0, 4), dtype=np.float64)]
    for index in occupied.tolist():
        y0, x0 = (index // tiles_x) * tile, (index % tiles_x) * tile
        y, x = max(y0 - margin, 0), max(x0 - margin, 0)
        lines = cv2.HoughLinesP(
            edges[y - rows_at : y0 + tile + margin - rows_at, x - cols_at : x0 + tile + margin - cols_at],
            1.0,
            math.pi / 180.0,
            votes,
            minLineLength=min_line_length,
            maxLineGap=max_line_gap,
        )
        if lines is not None:
            found.append(lines.reshape(-1, 4).astype(np.float64) + np.array([x, y, x, y]))
    return np.concatenate(found)


def _occupied_part(image: npt.NDArray[np.uint8], tile: int) -> tuple[slice, slice] | None:
    """The rows and columns of ``image`` that hold every window of :func:`_tiled_hough` that can
    see an edge: edges lie within two pixels of occupied ones (3x3 blur, 3x3 Sobel; frontiers
    between free and unknown stay below Canny's thresholds), windows reach a quarter tile past
    their tile. None when nothing is occupied."""
    import cv2

    x, y, width, height = cv2.boundingRect((image == OCCUPIED).view(np.uint8))
    if width == 0:
        return None
    reach = 2 + 1  # edge pixels beyond occupied ones, and one for the blur's own border
    margin = tile // 4

    def span(low: int, high: int, size: int) -> slice:
        first_tile = max(low - reach, 0) // tile * tile
        last_tile = (min(high + reach, size - 1) // tile + 1) * tile
        return slice(max(first_tile - margin, 0), min(last_tile + margin, size))

    return span(y, y + height - 1, image.shape[0]), span(x, x + width - 1, image.shape[1])


def detect_segments(
    image: npt.NDArray[np.uint8],
    *,
    canny_low: float = 150.0,
    canny_high: float = 250.0,
    votes: int = 8,
    min_line_length: float = 4.0,
    max_line_gap: float = 2.0,
    tile: int = 64,
) -> Float64Array:
    """Edge segments (x0, y0, x1, y1) in pixels, shape (N, 4); Hough at 1 px and 1 degree.

    The blur gives Canny one gradient peak per side of a wall: on the raw two-level image a wall
    two cells thick has a flat gradient plateau, and non-maximum suppression picks arbitrary
    rows of it; a one-cell diagonal (a staircase) breaks into fragments.

    HoughLinesP misbehaves on whole floor plans in two ways, both measured on the benchmark
    plan and the test grids. Its accumulator collects votes from every wall on the same line
    of the image, so about a sixth of the wall edges went undetected; it runs per ``tile`` x
    ``tile`` window instead. And a sampled pixel whose strongest angle belongs to another
    wall (at a corner) walks off its edge and erases the pixels it passes without reporting
    them: the first cells of an L corner went missing. So edge pixels are split by gradient
    direction into four overlapping classes (0, 45, 90, 135 degrees, +-45 each) searched
    separately: any straight edge lies wholly in one class, crossing walls never share one.
    Walls cut at window borders, and the doubles of overlapping windows and classes, are
    joined again by the merge.
    """
    import cv2

    part = _occupied_part(image, tile)
    if part is None:
        return np.zeros((0, 4), dtype=np.float64)
    blurred = cv2.GaussianBlur(image[part], (3, 3), 0)
    # The derivatives Canny computes for itself (3x3 Sobel, 16-bit, replicated border), made
    # once: they give the edge directions too.
    dx = cv2.Sobel(blurred, cv2.CV_16S, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    dy = cv2.Sobel(blurred, cv2.CV_16S, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    edges = cv2.Canny(dx, dy, canny_low, canny_high, L2gradient=True)
    rows, cols = np.nonzero(edges)
    # Edge direction modulo 180 degrees (the gradient turned by 90 degrees).
    direction = (np.degrees(np.arctan2(dy[rows, cols], dx[rows, cols])) + 90.0) % 180.0
    found = []
    origin = (part[0].start, part[1].start)
    for centre in (0.0, 45.0, 90.0, 135.0):
        keep = np.abs((direction - centre + 90.0) % 180.0 - 90.0) < 45.0
        found.append(
            _tiled_hough(
                edges.shape,
                rows=rows[keep],
                cols=cols[keep],
                origin=origin,
                shape=image.shape,
                votes=votes,
                min_line_length=min_line_length,
                max_line_gap=max_line_gap,
                tile=tile,
            )
        )
    return np.concatenate(found)


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
    """Extend wall ends that stop short of a crossing wall to that wall's centre line.

    The edges of a wall stop at the edge of the wall they run into, so after merging, the walls
    of an L corner or a T junction end half a wall thickness and a cell short of each other.
    An end moves out to where its line meets the line of a segment at least ``min_angle_deg``
    away in direction, when that point is at most ``reach`` beyond the end and on the other
    segment or within ``reach`` of it; the nearest such point wins. Ends never move inwards,
    and segments that cross already are left alone.
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
    before = on_b & (t < 0.0) & (t >= -reach)
    beyond = on_b & (t > g.length[a]) & (t <= g.length[a] + reach)
    seg = np.concatenate([a[before], a[beyond]])
    end = np.concatenate([np.zeros(before.sum(), np.intp), np.ones(beyond.sum(), np.intp)])
    t_end = np.concatenate([t[before], t[beyond]])
    extension = np.concatenate([-t[before], t[beyond] - g.length[a[beyond]]])
    order = np.lexsort((extension, end, seg))
    seg, end, t_end = seg[order], end[order], t_end[order]
    first = np.ones(seg.size, dtype=bool)
    first[1:] = (seg[1:] != seg[:-1]) | (end[1:] != end[:-1])
    seg, end, t_end = seg[first], end[first], t_end[first]
    points = g.p0[seg] + t_end[:, None] * u[seg]
    segs[seg[end == 0], :2] = points[end == 0]
    segs[seg[end == 1], 2:] = points[end == 1]
    return segs


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
    vertices = local @ rotation.T + np.asarray(translation, dtype=np.float64)
    normals = np.repeat(face_normals, 4, axis=1).reshape(-1, 3) @ rotation.T
    quad_starts = np.arange(n_boxes * 6) * 4
    triangles = (quad_starts[:, None, None] + _QUAD_TRIANGLES[None]).reshape(-1, 3)
    return WallMesh(
        vertices.astype(np.float32), triangles.astype(np.uint32), normals.astype(np.float32)
    )
