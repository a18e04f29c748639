"""Offline bag -> .rrd, whole process, against Rerun's own Rust MCAP importer run side by side.

Baseline: ``rerun mcap convert BAG.mcap -o out.rrd`` (the ``rerun`` beside this Python).
Ours: ``swanky-host --bag BAG.mcap --save out.rrd``, the installed command, interpreter start-up
included (the issue's target 1 is whole-process). Rounds alternate baseline and ours (the shared
machine's load drifts); each file's ratio is the median over the rounds of
baseline seconds / ours seconds, so 1.0 means as fast as Rerun's importer and higher is better.

The two files of issue 13 are written here, deterministically, with rosbags' Writer (rosbag2,
MCAP storage, message definitions included, so both tools decode them):

- small messages: 300k Imu at 200 Hz, 100k TFMessage (2 transforms), 50k JointState (6 joints),
  20k NavSatFix, spread over the same 1500 s;
- large messages: 300 Image 640x480 rgb8 at 30 Hz and 100 PointCloud2 of 100k points at 10 Hz
  (PCL's PointXYZRGB layout: x, y, z float32, packed rgb at offset 16, point_step 32).

``--small-scale`` and ``--large-scale`` multiply each file's message counts; both default to 1.0,
the issue's sizes (470,000 small messages: swanky-host took 6 s of them in November 2026, so
three rounds, the files' generation and the comparison fit the budget). Targets: small >= 0.5,
large >= 1.0.

After the timing both .rrd files are read back and compared where both tools convert a type:
rows matched by log time and their values (Rerun's importer logs its own archetypes at the topic
names, Swanky its own under /robot; what only one logs is named, not compared).

    .venv/bin/python benchmarks/bag_conversion.py [--small-scale 1] [--large-scale 1] [--rounds 3]
    .venv/bin/python benchmarks/bag_conversion.py --keep /tmp/bags   # keep the files, to profile
    .venv/bin/python benchmarks/bag_conversion.py BAG.mcap ...   # your own files instead
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from startup import ENV  # beside this script

# python -m benchmarks gives each script this many seconds at most.
BUDGET_SECONDS = 300

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
START_NS = 1_700_000_000 * 10**9
SMALL_SPAN_S = 1500.0  # 300k Imu at 200 Hz
TARGETS = {"small": 0.5, "large": 1.0}
IMAGE_WIDTH, IMAGE_HEIGHT = 640, 480
CLOUD_POINTS = 100_000
CLOUD_POINT_STEP = 32
JOINTS = [f"joint_{i}" for i in range(6)]


@dataclass(frozen=True, slots=True)
class Topic:
    name: str
    msgtype: str
    count: int
    make: Callable[[int, int], Any]  # (index, stamp ns) -> message


def header(stamp_ns: int, frame_id: str) -> Any:
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def vector3(x: float, y: float, z: float) -> Any:
    return T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def yaw_quaternion(yaw: float) -> Any:
    return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=float(np.sin(yaw / 2)),
                                             w=float(np.cos(yaw / 2)))


def small_topics(scale: float) -> list[Topic]:
    covariance = np.linspace(0.0, 0.08, 9)

    def imu(i: int, stamp: int) -> Any:
        phase = i * 0.005
        return T["sensor_msgs/msg/Imu"](
            header=header(stamp, "imu_link"), orientation=yaw_quaternion(0.1 * phase),
            orientation_covariance=covariance,
            angular_velocity=vector3(0.01 * np.sin(phase), 0.02 * np.cos(phase), 0.1),
            angular_velocity_covariance=covariance,
            linear_acceleration=vector3(0.2 * np.cos(phase), 0.1 * np.sin(3 * phase), 9.81),
            linear_acceleration_covariance=covariance,
        )

    def transform(stamp: int, parent: str, child: str, x: float, yaw: float) -> Any:
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=vector3(x, 0.5 * x, 0.0), rotation=yaw_quaternion(yaw)),
        )

    def tf(i: int, stamp: int) -> Any:
        phase = i * 0.015
        return T["tf2_msgs/msg/TFMessage"](transforms=[
            transform(stamp, "map", "odom", 0.001 * phase, 0.0001 * phase),
            transform(stamp, "odom", "base_link", np.sin(0.1 * phase), 0.1 * phase),
        ])

    def joint_state(i: int, stamp: int) -> Any:
        phase = i * 0.03
        angles = np.sin(phase + np.arange(len(JOINTS)))
        return T["sensor_msgs/msg/JointState"](
            header=header(stamp, ""), name=JOINTS, position=angles,
            velocity=np.cos(phase + np.arange(len(JOINTS))), effort=0.1 * angles,
        )

    def nav_sat_fix(i: int, stamp: int) -> Any:
        return T["sensor_msgs/msg/NavSatFix"](
            header=header(stamp, "gps"),
            status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
            latitude=48.8566 + 1e-6 * i, longitude=2.3522 + 2e-6 * i, altitude=35.0 + 0.001 * i,
            position_covariance=covariance, position_covariance_type=2,
        )

    return [
        Topic("/imu", "sensor_msgs/msg/Imu", scaled(300_000, scale), imu),
        Topic("/tf", "tf2_msgs/msg/TFMessage", scaled(100_000, scale), tf),
        Topic("/joint_states", "sensor_msgs/msg/JointState", scaled(50_000, scale), joint_state),
        Topic("/gps/fix", "sensor_msgs/msg/NavSatFix", scaled(20_000, scale), nav_sat_fix),
    ]


def large_topics(scale: float) -> list[Topic]:
    rng = np.random.default_rng(13)
    rows, cols = np.mgrid[0:IMAGE_HEIGHT, 0:IMAGE_WIDTH]
    base_image = np.stack([cols * 255 // IMAGE_WIDTH, rows * 255 // IMAGE_HEIGHT,
                           (rows + cols) % 256], axis=-1).astype(np.uint8)
    points = np.zeros(CLOUD_POINTS, dtype=np.dtype({
        "names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<u4"],
        "offsets": [0, 4, 8, 16], "itemsize": CLOUD_POINT_STEP}))
    xyz = rng.normal(0.0, 3.0, size=(CLOUD_POINTS, 3)).astype(np.float32)
    colours = rng.integers(0, 1 << 24, size=CLOUD_POINTS, dtype=np.uint32)

    def image(i: int, stamp: int) -> Any:
        pixels = np.roll(base_image, 4 * i, axis=1)
        return T["sensor_msgs/msg/Image"](
            header=header(stamp, "camera_optical"), height=IMAGE_HEIGHT, width=IMAGE_WIDTH,
            encoding="rgb8", is_bigendian=0, step=3 * IMAGE_WIDTH, data=pixels.reshape(-1))

    def cloud(i: int, stamp: int) -> Any:
        for axis, name in enumerate("xyz"):
            points[name] = xyz[:, axis] + 0.01 * i
        points["rgb"] = np.roll(colours, i)
        fields = [T["sensor_msgs/msg/PointField"](name=name, offset=offset, datatype=7, count=1)
                  for name, offset in (("x", 0), ("y", 4), ("z", 8), ("rgb", 16))]
        return T["sensor_msgs/msg/PointCloud2"](
            header=header(stamp, "lidar"), height=1, width=CLOUD_POINTS, fields=fields,
            is_bigendian=False, point_step=CLOUD_POINT_STEP, row_step=CLOUD_POINT_STEP * CLOUD_POINTS,
            data=points.view(np.uint8), is_dense=True)

    return [
        Topic("/camera/image_raw", "sensor_msgs/msg/Image", scaled(300, scale), image),
        Topic("/points", "sensor_msgs/msg/PointCloud2", scaled(100, scale), cloud),
    ]


def scaled(count: int, scale: float) -> int:
    return max(1, round(count * scale))


def stamps(topic: Topic, span_ns: int) -> npt.NDArray[np.int64]:
    """Evenly spaced record times over the span, offset per topic so no two topics tie."""
    step = span_ns // topic.count
    offset = sum(map(ord, topic.name)) % step if step else 0
    return START_NS + offset + step * np.arange(topic.count, dtype=np.int64)


def in_time_order(topics: list[Topic], span_ns: int) -> Iterator[tuple[int, int, int]]:
    """(record time, topic index, message index) of every message, oldest first."""
    times = [stamps(topic, span_ns) for topic in topics]
    which = np.concatenate([np.full(t.size, k) for k, t in enumerate(times)])
    index = np.concatenate([np.arange(t.size) for t in times])
    when = np.concatenate(times)
    for j in np.argsort(when, kind="stable"):
        yield int(when[j]), int(which[j]), int(index[j])


def write_bag(directory: Path, topics: list[Topic], span_ns: int) -> None:
    """A rosbag2 bag with MCAP storage at ``directory``."""
    with Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = [writer.add_connection(t.name, t.msgtype, typestore=STORE) for t in topics]
        for stamp, k, i in in_time_order(topics, span_ns):
            topic = topics[k]
            writer.write(connections[k], stamp,
                         STORE.serialize_cdr(topic.make(i, stamp), topic.msgtype))


def generated_bags(root: Path, small_scale: float, large_scale: float) -> dict[str, Path]:
    """The .mcap files of the issue's two bags under ``root``, written unless an earlier run
    finished them there (rosbags writes metadata.yaml last)."""
    recipes = {
        "small": (small_scale, small_topics, SMALL_SPAN_S * small_scale),
        "large": (large_scale, large_topics, scaled(300, large_scale) / 30),  # images at 30 Hz
    }
    bags = {}
    for label, (scale, topics, span_s) in recipes.items():
        directory = root / f"{label}-{scale:g}"
        if not (directory / "metadata.yaml").exists():
            shutil.rmtree(directory, ignore_errors=True)
            write_bag(directory, topics(scale), int(span_s * 1e9))
        bags[label] = next(directory.glob("*.mcap"))
    return bags


def message_count(bag: Path) -> int:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag], default_typestore=STORE) as reader:
        return int(reader.message_count)


@dataclass(frozen=True, slots=True)
class Pair:
    """One thing both tools log for the same messages: Rerun's importer's (entity, component,
    columns of its value) and Swanky's (entity, component) parts, side by side."""

    what: str
    theirs: tuple[str, str]
    ours: tuple[tuple[str, str], ...]
    their_columns: tuple[int, int] | None = None  # [start, stop) of Rerun's value, else all
    tolerance: float = 1e-6  # float32 in one tool, float64 in the other
    as_colour: bool = False  # Rerun keeps PointCloud2's packed rgb field as a float


def _joints(field: str) -> tuple[tuple[str, str], ...]:
    return tuple((f"/robot/joint_states/{joint}/{field}", "Scalars:scalars") for joint in JOINTS)


# Rerun's importer logs a topic at its name with its own archetypes; Swanky at /robot/<topic>.
PAIRS = [
    Pair("Imu angular_velocity", ("/imu", "Scalars:scalars"),
         (("/robot/imu/angular_velocity", "Scalars:scalars"),), (0, 3)),
    Pair("Imu linear_acceleration", ("/imu", "Scalars:scalars"),
         (("/robot/imu/linear_acceleration", "Scalars:scalars"),), (3, 6)),
    Pair("Imu orientation", ("/imu", "sensor_msgs.msg.Imu:orientation"),
         (("/robot/imu/orientation", "Transform3D:quaternion"),)),
    Pair("TFMessage translation", ("/tf", "Transform3D:translation"),
         (("/robot/tf", "Transform3D:translation"),)),
    Pair("TFMessage rotation", ("/tf", "Transform3D:quaternion"),
         (("/robot/tf", "Transform3D:quaternion"),)),
    Pair("JointState position", ("/joint_states/position", "Scalars:scalars"), _joints("position")),
    Pair("JointState velocity", ("/joint_states/velocity", "Scalars:scalars"), _joints("velocity")),
    Pair("JointState effort", ("/joint_states/effort", "Scalars:scalars"), _joints("effort")),
    Pair("NavSatFix latitude, longitude", ("/gps/fix", "GeoPoints:positions"),
         (("/robot/gps/fix", "GeoPoints:positions"),)),
    Pair("NavSatFix altitude", ("/gps/fix", "altitude"),
         (("/robot/gps/fix/altitude", "Scalars:scalars"),)),
    Pair("Image pixels", ("/camera/image_raw", "Image:buffer"),
         (("/robot/camera/image_raw", "Image:buffer"),), tolerance=0.0),
    Pair("PointCloud2 positions", ("/points", "Points3D:positions"),
         (("/robot/points", "Points3D:positions"),), tolerance=0.0),
    Pair("PointCloud2 colours", ("/points", "Points3D:rgb"),
         (("/robot/points", "Points3D:colors"),), tolerance=0.0, as_colour=True),
]
NOT_COMPARED = (
    "not compared: what one tool logs and the other does not (Swanky's IMU arrows and GPS radii, "
    "Rerun's McapChannel/McapSchema rows and raw PointCloud2 fields), frame names (Swanky "
    "prefixes them with the robot: robot/odom), the image format and the header-stamp timeline"
)


def _rows(column: Any) -> npt.NDArray[Any] | None:
    """A list column of valid rows as one row of primitive values per row; None when the rows
    hold different numbers of values."""
    import pyarrow as pa

    lengths = column.value_lengths().to_numpy(zero_copy_only=False)
    if len(lengths) and (lengths != lengths[0]).any():
        return None
    values = column.flatten()
    while pa.types.is_list(values.type) or pa.types.is_fixed_size_list(values.type):
        values = values.flatten()
    return values.to_numpy(zero_copy_only=False).reshape(len(column), -1)  # type: ignore[no-any-return]


def rrd_values(path: Path, wanted: set[tuple[str, str]], time_column: str) -> dict[
        tuple[str, str], tuple[npt.NDArray[np.int64], npt.NDArray[Any]]]:
    """(log times, one row of values per row) of each wanted (entity, component) of a .rrd, rows
    sorted by log time then value; chunks whose rows differ in length are left out."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    parts: dict[tuple[str, str], list[tuple[npt.NDArray[np.int64], npt.NDArray[Any]]]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if (chunk.entity_path, name) not in wanted:
                continue
            column = batch.column(name)
            valid = column.is_valid()
            values = _rows(column.filter(valid))
            if values is not None:
                times = batch.column(time_column).cast(pa.int64()).filter(valid).to_numpy()
                parts.setdefault((chunk.entity_path, name), []).append((times, values))
    found = {}
    for key, pieces in parts.items():
        width = max(values.shape[1] for _, values in pieces)
        times = np.concatenate([t for t, v in pieces if v.shape[1] == width])
        values = np.concatenate([v for _, v in pieces if v.shape[1] == width])
        order = np.lexsort((*values.T[::-1], times)) if width <= 8 else np.argsort(times, kind="stable")
        found[key] = (times[order], values[order])
    return found


def compare_outputs(theirs_path: Path, ours_path: Path) -> None:
    """Print, per thing both tools convert, whether both .rrd files hold the same rows (by log
    time) and the same values; what only one tool logs is not compared (said so)."""
    theirs = rrd_values(theirs_path, {pair.theirs for pair in PAIRS}, "message_log_time")
    ours = rrd_values(ours_path, {part for pair in PAIRS for part in pair.ours}, "log_time")
    print("  same rows and values in both .rrd files (rows matched by log time):")
    for pair in PAIRS:
        if pair.theirs not in theirs:
            if any(part in ours for part in pair.ours):
                print(f"    {pair.what:32s} Rerun none, Swanky {len(ours[pair.ours[0]][0]):>9,} rows")
            continue  # else the topic is not in this bag
        their_times, their_values = theirs[pair.theirs]
        if pair.their_columns is not None:
            their_values = their_values[:, slice(*pair.their_columns)]
        pieces = [ours[part] for part in pair.ours if part in ours]
        if len(pieces) < len(pair.ours):
            print(f"    {pair.what:32s} Rerun {len(their_times):>9,} rows, Swanky none: DIFFER")
            continue
        our_times = pieces[0][0]
        our_values = np.hstack([values for _, values in pieces])
        rows = f"rows Rerun {len(their_times):>9,} Swanky {len(our_times):>9,}"
        if their_values.shape != our_values.shape or not np.array_equal(their_times, our_times):
            print(f"    {pair.what:32s} {rows}, values {their_values.shape} vs {our_values.shape}: "
                  "DIFFER")
            continue
        if pair.as_colour:
            packed = np.ascontiguousarray(their_values, np.float32).view(np.uint32)
            their_values = (packed << 8) | 0xFF
        difference = np.abs(their_values.astype(np.float64) - our_values.astype(np.float64))
        worst = float(difference.max()) if difference.size else 0.0
        scale = max(float(np.abs(their_values).max()) if their_values.size else 0.0, 1.0)
        verdict = "match" if worst <= pair.tolerance * scale else "DIFFER"
        print(f"    {pair.what:32s} {rows}, {our_values.size:>11,} values, max |difference| "
              f"{worst:.3g}: {verdict}")
    print(f"  {NOT_COMPARED}", flush=True)


def timed(command: list[str]) -> float:
    started = time.perf_counter()
    # Both commands are Python entry points of the venv: run them as on a user's install,
    # without the [ros-test] wheels' bootstrap re-executing the interpreter (startup.py).
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=ENV)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        msg = f"{' '.join(command)} exited {done.returncode}:\n{done.stderr[-2000:]}"
        raise RuntimeError(msg)
    return elapsed


def compare(label: str, bag: Path, rounds: int, tools: dict[str, str], out: Path) -> None:
    count = message_count(bag)
    size_mb = bag.stat().st_size / 1e6
    baseline_runs: list[float] = []
    ours_runs: list[float] = []
    for _ in range(rounds):
        baseline_runs.append(timed([tools["rerun"], "mcap", "convert", str(bag),
                                    "-o", str(out / "rerun.rrd")]))
        ours_runs.append(timed([tools["swanky-host"], "--bag", str(bag),
                                "--save", str(out / "swanky.rrd")]))
    baseline, ours = statistics.median(baseline_runs), statistics.median(ours_runs)
    ratio = statistics.median(b / o for b, o in zip(baseline_runs, ours_runs, strict=True))
    target = TARGETS.get(label)
    verdict = "" if target is None else f" (target >= {target}: {'met' if ratio >= target else 'MISSED'})"
    print(f"{label}: {bag.name}, {count:,} messages, {size_mb:,.0f} MB")
    print(f"  baseline rerun mcap convert: {baseline:7.2f} s ({count / baseline:>10,.0f} msg/s), "
          f"runs {', '.join(f'{t:.2f}' for t in baseline_runs)}")
    print(f"  swanky-host --bag --save:    {ours:7.2f} s ({count / ours:>10,.0f} msg/s), "
          f"runs {', '.join(f'{t:.2f}' for t in ours_runs)}")
    print(f"  ratio {label} rerun/swanky wall time, median of {rounds}: {ratio:.3f}{verdict}",
          flush=True)
    compare_outputs(out / "rerun.rrd", out / "swanky.rrd")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bags", nargs="*", type=Path,
                        help="compare on these .mcap files instead of generating the two")
    parser.add_argument("--small-scale", type=float, default=1.0,
                        help="multiply the small-message file's counts (1.0: the issue's 470k)")
    parser.add_argument("--large-scale", type=float, default=1.0,
                        help="multiply the large-message file's counts (1.0: the issue's 400)")
    parser.add_argument("--rounds", type=int, default=3, help="baseline and ours, this many times")
    parser.add_argument("--keep", type=Path, metavar="DIR",
                        help="write the generated bags under DIR and keep them (reused by the next "
                             "run with the same scale; handy for profiling one conversion)")
    args = parser.parse_args()
    bin_dir = Path(sys.executable).parent
    tools = {name: shutil.which(name, path=str(bin_dir)) for name in ("rerun", "swanky-host")}
    missing = [name for name, path in tools.items() if path is None]
    if missing:
        print(f"needs {' and '.join(missing)} in {bin_dir} (pip install -e '.[host]')",
              file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="swanky_bench_") as tmp:
        out = Path(tmp)
        if args.bags:
            bags = {bag.stem: bag for bag in args.bags}
        else:
            started = time.perf_counter()
            bags = generated_bags(args.keep or out, args.small_scale, args.large_scale)
            print(f"the issue's two files, small at scale {args.small_scale}, large at scale "
                  f"{args.large_scale}, ready in {time.perf_counter() - started:.1f} s", flush=True)
        for label, bag in bags.items():
            compare(label, bag, args.rounds, {k: str(v) for k, v in tools.items()}, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
