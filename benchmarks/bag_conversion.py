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

``--small-scale`` and ``--large-scale`` multiply each file's message counts (1.0 is the issue's
size). The small file defaults to 0.25 (117,500 messages) so that three rounds stay within the
benchmark's time budget while swanky-host needs about 0.2 ms per small message (November 2026);
at that scale Rerun's importer takes about 0.25 s, and swanky-host's start-up (about 2 s of
imports) weighs more in the ratio than at the full 470k. Targets: small >= 0.5, large >= 1.0.

    .venv/bin/python benchmarks/bag_conversion.py [--small-scale 0.25] [--large-scale 1] [--rounds 3]
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


def timed(command: list[str]) -> float:
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bags", nargs="*", type=Path,
                        help="compare on these .mcap files instead of generating the two")
    parser.add_argument("--small-scale", type=float, default=0.25,
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
