"""The heavy converters alone against per-element Python loops of the kind a naive ROS node runs.

Ours: the registry's converter of each type (``default_registry()``), on messages decoded by
rosbags exactly as the dispatcher decodes them (numpy views over the CDR buffer), with contexts
made like the dispatcher's (``tests/host_bridge/sensor_test_support.make_ctx``). Each call
returns the Rerun archetypes (Arrow arrays built) that the sink would log.

Baselines, timed in the same run on the same messages (``struct`` on the same buffer):

- PointCloud2: a loop over the points unpacking x, y, z and the packed rgb word with one
  ``struct.Struct`` each, skipping non-finite points (ROS 1 ``point_cloud2.read_points``), then
  ``rr.Points3D`` of the lists.
- Image: a loop over the pixels unpacking each pixel's channels (one ``struct.Struct`` per
  encoding: 3 bytes, one little-endian word, one YUV422 pair, one Bayer byte) into per-row lists.
  It converts no colour at all, so for yuv422 and Bayer it does less than ours (the baseline is
  flattered). Timed on the first 48 rows and scaled to the full 480 (a full frame takes seconds).
- LaserScan: a loop over the rays keeping ``range_min <= r < range_max``, computing
  ``(r cos a, r sin a, 0)`` and a colour by range from a 256-entry turbo table (ours' default
  colouring), then ``rr.Points3D``: the same output as ours. Ours is timed on a run of 100
  scans (one ``Points3D`` column partitioned by scan, as the dispatcher converts a bag's run of
  scans or a live backlog), which is judged against the target: a converter takes runs (the
  contract, host_bridge/core/contract.py). A run of one scan (one ``Points3D``, what a live scan
  that arrives by itself costs) is printed for comparison: its
  fixed cost per call (building the points for one scan, its colours, the archetype, ~0.1 ms)
  is what the run form spreads over its scans.
- OccupancyGrid 4000x4000: ours is the GridMap and the wall mesh (the registry row's converter
  and its slow converter, a fresh robot state each time so no cache helps); the baseline a loop
  over the cells turning occupancy values into RGBA (no walls), on every 100th row (40 rows across
  rooms, walls and the unknown border) scaled to 4000. Ratios are given for the GridMap alone
  and for GridMap + walls.

Rates are medians of several timing rounds (``time.perf_counter``); each line gives the target
of issue 13 and the ratio ours/baseline in the same unit. Run:
``.venv/bin/python benchmarks/converters.py [--rounds 5]``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import struct
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import rerun as rr
from rosbags.typesys import Stores, get_typestore

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests/ for make_ctx

from walls_4000 import RESOLUTION, SIZE, floor_plan

from host_bridge.core.colormap import apply_colormap
from host_bridge.core.contract import ConvertContext
from host_bridge.table.registry import default_registry
from tests.host_bridge.sensor_test_support import convert, convert_run, header, make_ctx, msg

BUDGET_SECONDS = 180

STORE = get_typestore(Stores.ROS2_HUMBLE)
REGISTRY = default_registry()
CLOUD_POINTS = 300_000
IMAGE_WIDTH, IMAGE_HEIGHT = 640, 480
IMAGE_SAMPLE_ROWS = 48
SCAN_RAYS = 720
SCAN_RUN = 100  # scans per run in the run form
MAP_SAMPLE_EVERY = 100  # rows
TARGETS = {"cloud": 200.0, "image": 1000.0, "scan": 50_000.0}  # per second
MAP_TARGET_MS = 200.0
# struct format of one unit the per-pixel loop reads: (format, pixels per unit).
PIXEL_FORMATS = {
    "rgb8": ("3B", 1), "bgr8": ("3B", 1), "mono16": ("<H", 1), "16UC1": ("<H", 1),
    "yuv422": ("4B", 2), "bayer_rggb8": ("B", 1), "bayer_rggb16": ("<H", 1),
}
# Occupancy -> RGBA as a naive node draws a map: unknown grey, free white, occupied dark.
UNKNOWN_RGBA, FREE_RGBA = (128, 128, 128, 255), (255, 255, 255, 255)


def decoded(message: Any, msgtype: str) -> Any:
    """``message`` after a CDR round trip: arrays are numpy views, as the dispatcher hands them."""
    return STORE.deserialize_cdr(STORE.serialize_cdr(message, msgtype), msgtype)


def seconds_per_call(fn: Callable[[], object], rounds: int, min_round_s: float = 0.2) -> float:
    """Median over ``rounds`` of the mean time per call in a round of at least ``min_round_s``."""
    fn()  # warm-up: first-call imports and caches
    per_call = []
    for _ in range(rounds):
        calls, started = 0, time.perf_counter()
        while True:
            fn()
            calls += 1
            elapsed = time.perf_counter() - started
            if elapsed >= min_round_s:
                break
        per_call.append(elapsed / calls)
    return statistics.median(per_call)


def report(label: str, unit: str, ours_s: float, baseline_s: float, target: float | None) -> None:
    """One line; ``target`` None: a figure printed for comparison, not judged."""
    ours, baseline = 1.0 / ours_s, 1.0 / baseline_s
    verdict = ("for comparison" if target is None else
               f"target >= {target:,.0f} {unit}: {'met' if ours >= target else 'MISSED'}")
    print(f"{label:<28} ours {ours:>10,.0f} {unit} ({ours_s * 1e3:8.3f} ms), loop baseline "
          f"{baseline:>8,.1f} {unit}; ratio ours/loop {ours / baseline:8.1f}; {verdict}", flush=True)


# --- point cloud ---------------------------------------------------------------------------------


def pcl_cloud(points: int) -> Any:
    """PCL's PointXYZRGB layout: x, y, z float32, 4 bytes padding, packed rgb, 12 bytes padding."""
    rng = np.random.default_rng(5)
    cloud = np.zeros(points, dtype=np.dtype({
        "names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<u4"],
        "offsets": [0, 4, 8, 16], "itemsize": 32}))
    for name in "xyz":
        cloud[name] = rng.normal(0.0, 5.0, points)
    cloud["x"][::97] = np.nan  # a few invalid returns, as a depth camera sends
    cloud["rgb"] = rng.integers(0, 1 << 24, points, dtype=np.uint32)
    fields = [msg("sensor_msgs/msg/PointField", name=n, offset=o, datatype=7, count=1)
              for n, o in (("x", 0), ("y", 4), ("z", 8), ("rgb", 16))]
    return decoded(msg("sensor_msgs/msg/PointCloud2", header=header("camera"), height=1,
                       width=points, fields=fields, is_bigendian=False, point_step=32,
                       row_step=32 * points, data=cloud.view(np.uint8), is_dense=False),
                   "sensor_msgs/msg/PointCloud2")


def cloud_loop(cloud: Any) -> rr.Points3D:
    xyz, rgb = struct.Struct("<3f"), struct.Struct("<I")
    data, step = cloud.data, int(cloud.point_step)
    positions: list[tuple[float, float, float]] = []
    colors: list[tuple[int, int, int]] = []
    for offset in range(0, int(cloud.width) * step, step):
        x, y, z = xyz.unpack_from(data, offset)
        if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
            (word,) = rgb.unpack_from(data, offset + 16)
            positions.append((x, y, z))
            colors.append(((word >> 16) & 0xFF, (word >> 8) & 0xFF, word & 0xFF))
    return rr.Points3D(positions, colors=colors)


def bench_cloud(rounds: int) -> None:
    cloud = pcl_cloud(CLOUD_POINTS)
    spec = REGISTRY.get("sensor_msgs/msg/PointCloud2")
    ctx = make_ctx("/points")
    ours = seconds_per_call(lambda: convert(spec, cloud, ctx), rounds)
    baseline = seconds_per_call(lambda: cloud_loop(cloud), min(rounds, 3), min_round_s=0.0)
    report(f"PointCloud2 {CLOUD_POINTS // 1000}k xyz+rgb", "clouds/s", ours, baseline,
           TARGETS["cloud"])


# --- images --------------------------------------------------------------------------------------


def image(encoding: str) -> Any:
    fmt, pixels_per_unit = PIXEL_FORMATS[encoding]
    bytes_per_pixel = struct.calcsize(fmt) // pixels_per_unit
    step = IMAGE_WIDTH * bytes_per_pixel
    data = np.random.default_rng(3).integers(0, 256, step * IMAGE_HEIGHT, dtype=np.uint8)
    return decoded(msg("sensor_msgs/msg/Image", header=header("camera_optical"),
                       height=IMAGE_HEIGHT, width=IMAGE_WIDTH, encoding=encoding, is_bigendian=0,
                       step=step, data=data), "sensor_msgs/msg/Image")


def pixel_loop(frame: Any, rows: int) -> list[list[tuple[int, ...]]]:
    fmt, pixels_per_unit = PIXEL_FORMATS[frame.encoding]
    unit = struct.Struct(fmt)
    data, step = frame.data, int(frame.step)
    row_bytes = int(frame.width) // pixels_per_unit * unit.size
    return [[unit.unpack_from(data, start + k) for k in range(0, row_bytes, unit.size)]
            for start in range(0, rows * step, step)]


def bench_images(rounds: int) -> None:
    spec = REGISTRY.get("sensor_msgs/msg/Image")
    for encoding in PIXEL_FORMATS:
        frame = image(encoding)
        ctx = make_ctx("/camera/image_raw")
        ours = seconds_per_call(lambda f=frame, c=ctx: convert(spec, f, c), rounds)  # type: ignore[misc]
        sample = seconds_per_call(lambda f=frame: pixel_loop(f, IMAGE_SAMPLE_ROWS),  # type: ignore[misc]
                                  min(rounds, 3), min_round_s=0.0)
        report(f"Image 640x480 {encoding}", "frames/s", ours,
               sample * IMAGE_HEIGHT / IMAGE_SAMPLE_ROWS, TARGETS["image"])


# --- laser scan ----------------------------------------------------------------------------------


def laser_scan(rays: int) -> Any:
    angles = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    ranges = (2.0 + np.sin(3 * angles)).astype(np.float32)
    ranges[::50] = np.inf  # no echo
    return decoded(msg("sensor_msgs/msg/LaserScan", header=header("laser"), angle_min=0.0,
                       angle_max=float(angles[-1]), angle_increment=float(angles[1]),
                       time_increment=0.0, scan_time=0.1, range_min=0.12, range_max=12.0,
                       ranges=ranges, intensities=np.zeros(0, dtype=np.float32)),
                   "sensor_msgs/msg/LaserScan")


TURBO = [tuple(rgb) for rgb in apply_colormap(np.arange(256), 0, 255, "turbo").tolist()]


def scan_loop(scan: Any) -> rr.Points3D:
    points: list[tuple[float, float, float]] = []
    colors: list[tuple[int, ...]] = []
    angle, increment = float(scan.angle_min), float(scan.angle_increment)
    low, high = float(scan.range_min), float(scan.range_max)
    for r in scan.ranges.tolist():
        if low <= r < high:
            points.append((r * math.cos(angle), r * math.sin(angle), 0.0))
            colors.append(TURBO[int((r - low) / (high - low) * 255.0)])
        angle += increment
    return rr.Points3D(points, colors=colors)


def bench_scan(rounds: int) -> None:
    scan = laser_scan(SCAN_RAYS)
    spec = REGISTRY.get("sensor_msgs/msg/LaserScan")
    ctx = make_ctx("/scan")
    ours = seconds_per_call(lambda: convert(spec, scan, ctx), rounds)
    baseline = seconds_per_call(lambda: scan_loop(scan), rounds)
    report(f"LaserScan {SCAN_RAYS} rays alone", "scans/s", ours, baseline, None)
    # The run form, as the dispatcher calls it on a bag's (or a busy link's) run of scans.
    scans = [laser_scan(SCAN_RAYS) for _ in range(SCAN_RUN)]
    ctxs = [make_ctx("/scan") for _ in scans]
    run = seconds_per_call(lambda: convert_run(spec, scans, ctxs), rounds) / SCAN_RUN
    report(f"LaserScan run of {SCAN_RUN}", "scans/s", run, baseline, TARGETS["scan"])


# --- occupancy grid ------------------------------------------------------------------------------


def occupancy_grid(cells: npt.NDArray[np.int8]) -> Any:
    origin = msg("geometry_msgs/msg/Pose",
                 position=msg("geometry_msgs/msg/Point", x=-100.0, y=-100.0, z=0.0),
                 orientation=msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
    info = msg("nav_msgs/msg/MapMetaData", map_load_time=header().stamp, resolution=RESOLUTION,
               width=cells.shape[1], height=cells.shape[0], origin=origin)
    return decoded(msg("nav_msgs/msg/OccupancyGrid", header=header("map"), info=info,
                       data=cells.ravel()), "nav_msgs/msg/OccupancyGrid")


def cell_loop(grid: Any, every: int) -> list[tuple[int, int, int, int]]:
    """RGBA of the cells of every ``every``-th row."""
    colors = []
    rows = grid.data.reshape(int(grid.info.height), int(grid.info.width))[::every]
    for value in rows.ravel().tolist():
        if value < 0:
            colors.append(UNKNOWN_RGBA)
        else:
            shade = 255 - value * 255 // 100
            colors.append(FREE_RGBA if value == 0 else (shade, shade, shade, 255))
    return colors


def bench_map(rounds: int) -> None:
    grid = occupancy_grid(floor_plan(np.random.default_rng(7)))
    row = REGISTRY.row("nav_msgs/msg/OccupancyGrid", "/map")
    walls = row.slow
    assert walls is not None, "the OccupancyGrid row has no wall converter"

    def convert_fresh() -> None:
        ctx: ConvertContext = make_ctx("/map")  # a fresh robot state: no wall cache
        convert(row.converter, grid, ctx)
        convert(walls, grid, ctx)

    map_rounds = max(3, rounds // 2)
    grid_only = seconds_per_call(lambda: convert(row.converter, grid, make_ctx("/map")), map_rounds, 0.0)
    ours = seconds_per_call(convert_fresh, map_rounds, min_round_s=0.0)
    baseline = MAP_SAMPLE_EVERY * seconds_per_call(lambda: cell_loop(grid, MAP_SAMPLE_EVERY), 3, 0.0)
    verdict = "met" if ours * 1e3 <= MAP_TARGET_MS else "MISSED"
    print(f"OccupancyGrid {SIZE}x{SIZE} -> GridMap + walls: ours {ours * 1e3:.0f} ms (GridMap alone "
          f"{grid_only * 1e3:.1f} ms), cell loop baseline {baseline * 1e3:,.0f} ms; ratio loop/ours "
          f"{baseline / ours:.2f} (GridMap alone {baseline / grid_only:.0f}); "
          f"target <= {MAP_TARGET_MS:.0f} ms: {verdict}", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="timing rounds per figure (median)")
    args = parser.parse_args()
    bench_cloud(args.rounds)
    bench_images(args.rounds)
    bench_scan(args.rounds)
    bench_map(args.rounds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
