"""Offline bag -> .rrd, whole process, against Rerun's own Rust MCAP importer run side by side,
on bags of every layout users' tools write (issue 25).

Baseline: ``rerun mcap convert BAG.mcap -o out.rrd`` (the ``rerun`` beside this Python).
Ours: ``swanky-host --bag BAG_DIR --save out.rrd``, the installed command given the rosbag2
directory as a user gives it, interpreter start-up included (whole-process, as issue 13's
target 1). Rounds alternate baseline and ours (the shared machine's load drifts); each bag's
ratio is the median over the rounds of baseline seconds / ours seconds, so 1.0 means as fast as
Rerun's importer and higher is better.

The two files of issue 13 are written here, deterministically, with rosbags' Writer (rosbag2,
message definitions included, so both tools decode them):

- small messages: 300k Imu at 200 Hz, 100k TFMessage (2 transforms), 50k JointState (6 joints),
  20k NavSatFix, spread over the same 1500 s;
- large messages: 300 Image 640x480 rgb8 at 30 Hz and 100 PointCloud2 of 100k points at 10 Hz
  (PCL's PointXYZRGB layout: x, y, z float32, packed rgb at offset 16, point_step 32).

Each in six layouts (LAYOUTS), the same messages in each: rosbags' Writer defaults (MCAP,
uncompressed 1 MiB chunks); ``ros2 bag record``'s defaults (MCAP, uncompressed chunks of 768 KiB,
no chunk CRC: rosbag2_storage_mcap's mcap_storage.cpp since its 0.5.0, with the mcap library's
DefaultChunkSize); zstd chunks and lz4 chunks of 768 KiB (the chunked ones written again from the
first by Foxglove's ``mcap`` writer); rosbag2's ``--compression-mode file`` (the .mcap zstd'ed
whole, metadata.yaml saying so); sqlite3 (Humble's default storage). ``rerun mcap convert``
reads only MCAP files: for the last two its baseline is the same messages as the plain MCAP of
the first layout (said in the output). And the small file ten times over (4.7 million messages,
start-up amortised: its repetitions shifted in time, stamps included, not serialised anew).

Targets: small >= 0.5 and large >= 1.0 on every layout, the 10x file >= 1.0. ``--small-scale``
and ``--large-scale`` multiply each file's message counts (1.0: the issue's sizes).
``python -m benchmarks`` runs the defaults: every layout of both files ``--rounds 3`` times, the
10x file once (``--tenfold-rounds``, 0 leaves it out), each bag one round only once
ONE_ROUND_AFTER of ``--budget`` (BUDGET_SECONDS) has passed, said in its line. Under a load
average of 4-10 on the 2 shared cores (November 29 2026) the defaults took 574 s, 128 s of it
generating the bags.

After the timing of the layouts in ``--check-rows`` (rosbags and sqlite3: the two reading
paths unlike each other) both .rrd files are read back and compared where both tools convert a
type: rows matched by log time and their values (Rerun's importer logs its own archetypes at the
topic names, Swanky its own under /robot; what only one logs is named, not compared).

    .venv/bin/python benchmarks/bag_conversion.py [--small-scale 1] [--large-scale 1] [--rounds 3]
    .venv/bin/python benchmarks/bag_conversion.py --layouts sqlite3 --tenfold-rounds 0
    .venv/bin/python benchmarks/bag_conversion.py --keep /tmp/bags   # keep the bags, to profile
    .venv/bin/python benchmarks/bag_conversion.py BAG.mcap ...   # your own files instead
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from mcap.writer import CompressionType
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from startup import ENV  # beside this script

# python -m benchmarks gives each script this many seconds at most; past ONE_ROUND_AFTER of them
# each bag gets one round only, so that the last ones and the 10x file (generated in 55 s and
# timed in 35 s under load) are still timed within it.
BUDGET_SECONDS = 420
ONE_ROUND_AFTER = 0.55

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types
START_NS = 1_700_000_000 * 10**9
SMALL_SPAN_S = 1500.0  # 300k Imu at 200 Hz
TARGETS = {"small": 0.5, "large": 1.0, "tenfold": 1.0}
TENFOLD = 10  # the 10x small-message file (4.7 million messages): start-up amortised
TENFOLD_ROUNDS = 1
STAMP_SECONDS = struct.Struct("<i")  # builtin_interfaces/Time.sec in little-endian CDR
CHECK_ROWS = ("rosbags", "sqlite3")  # rows compared: the bulk reader's layout, and rosbags' path
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


@dataclass(frozen=True, slots=True)
class Layout:
    """One way users' tools lay a bag out on disk; every layout of a file holds the same
    messages. rosbags writes the first three kinds; the chunked ones are the rosbags MCAP written
    again, record for record, by Foxglove's ``mcap`` writer with other chunks."""

    name: str
    written_by: str
    storage: StoragePlugin = StoragePlugin.MCAP
    file_compression: bool = False  # rosbag2's compression_mode file: the .mcap zstd'ed whole
    chunk_size: int = 0  # > 0: chunked again with this size and chunk_compression
    chunk_compression: CompressionType = CompressionType.NONE

    @property
    def rerun_reads(self) -> bool:
        """Whether ``rerun mcap convert`` reads it: a plain .mcap file only."""
        return self.storage == StoragePlugin.MCAP and not self.file_compression


# rosbag2_storage_mcap's writer (mcap_storage.cpp, open_impl, since its 0.5.0 "defaults for SQLite
# plugin parity", so every Humble release since November 2022 and later distributions): no chunk
# compression, no chunk CRC, the mcap library's DefaultChunkSize of 768 KiB (mcap/types.hpp).
ROS2_RECORD_CHUNK = 768 * 1024
LAYOUTS = (
    Layout("rosbags", "rosbags' Writer defaults: uncompressed MCAP, 1 MiB chunks"),
    Layout("ros2-record", "ros2 bag record defaults: uncompressed MCAP, 768 KiB chunks",
           chunk_size=ROS2_RECORD_CHUNK),
    Layout("zstd-chunks", "MCAP, zstd chunks of 768 KiB (ros2 bag record's zstd presets)",
           chunk_size=ROS2_RECORD_CHUNK, chunk_compression=CompressionType.ZSTD),
    Layout("lz4-chunks", "MCAP, lz4 chunks of 768 KiB", chunk_size=ROS2_RECORD_CHUNK,
           chunk_compression=CompressionType.LZ4),
    Layout("file-zstd", "ros2 bag record --compression-mode file: the .mcap zstd'ed whole",
           file_compression=True),
    Layout("sqlite3", "ros2 bag record -s sqlite3 (Humble's default storage)",
           storage=StoragePlugin.SQLITE3),
)
REFERENCE = LAYOUTS[0]  # generated first; the others are written from it or beside it


def write_bag(directory: Path, topics: list[Topic], span_ns: int) -> None:
    """A rosbag2 bag with MCAP storage at ``directory``, rosbags' Writer defaults."""
    write_bags({REFERENCE: directory}, topics, span_ns)


def write_bags(directories: dict[Layout, Path], topics: list[Topic], span_ns: int) -> None:
    """The same messages, serialised once, as a rosbag2 bag of each layout rosbags writes
    (not chunked again) at its directory."""
    with ExitStack() as stack:
        writers = []
        for layout, directory in directories.items():
            writer = Writer(directory, version=9, storage_plugin=layout.storage)
            if layout.file_compression:
                writer.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
            stack.enter_context(writer)
            connections = [writer.add_connection(t.name, t.msgtype, typestore=STORE) for t in topics]
            writers.append((writer.write, connections))
        for stamp, k, i in in_time_order(topics, span_ns):
            topic = topics[k]
            data = STORE.serialize_cdr(topic.make(i, stamp), topic.msgtype)
            for write, connections in writers:
                write(connections[k], stamp, data)


def rechunk_bags(source: Path, directories: dict[Layout, Path]) -> None:
    """The rosbags bag at ``source`` written again into each directory with its layout's chunks:
    the same schemas, channels (their QoS metadata included) and message records; the bag's
    metadata.yaml beside it, naming the new file, written last."""
    from mcap.reader import make_reader
    from mcap.writer import Writer as McapWriter

    mcap_file = next(source.glob("*.mcap"))
    with ExitStack() as stack:
        reader = make_reader(stack.enter_context(mcap_file.open("rb")))
        summary = reader.get_summary()
        assert summary is not None
        writers = []
        for layout, directory in directories.items():
            directory.mkdir(parents=True)
            writer = McapWriter(str(directory / f"{directory.name}.mcap"),
                                chunk_size=layout.chunk_size,
                                compression=layout.chunk_compression, enable_crcs=False)
            writer.start(profile="ros2", library=reader.get_header().library)
            stack.callback(writer.finish)
            schemas = {schema_id: writer.register_schema(schema.name, schema.encoding, schema.data)
                       for schema_id, schema in summary.schemas.items()}
            channels = {channel_id: writer.register_channel(
                channel.topic, channel.message_encoding, schemas[channel.schema_id],
                dict(channel.metadata)) for channel_id, channel in summary.channels.items()}
            writers.append((writer.add_message, channels))
        for _, channel, message in reader.iter_messages(log_time_order=False):
            for add, channels in writers:
                add(channels[channel.id], message.log_time, message.data, message.publish_time,
                    message.sequence)
    metadata = (source / "metadata.yaml").read_text()
    for directory in directories.values():
        (directory / "metadata.yaml").write_text(
            metadata.replace(mcap_file.name, f"{directory.name}.mcap"))


def stamp_seconds(topic: Topic) -> list[int]:
    """Where a message of ``topic`` holds the seconds of its header stamps: the int32 words that
    differ between one message serialised at two stamps whole seconds apart."""
    first, later = (bytes(STORE.serialize_cdr(topic.make(0, START_NS + shift), topic.msgtype))
                    for shift in (0, 10**9))
    assert len(first) == len(later), topic.name
    return sorted({at - at % 4 for at in range(len(first)) if first[at] != later[at]})


def write_repeated(source: Path, directory: Path, topics: list[Topic], times: int,
                   shift_s: int) -> None:
    """The rosbags bag at ``source`` ``times`` over as one rosbags bag at ``directory``: each
    repetition ``shift_s`` whole seconds after the last, its log times and header stamps (their
    seconds, patched in the CDR) shifted so, its values the same. Serialising 4.7 million
    messages anew would take minutes; this takes seconds a million."""
    from mcap.reader import make_reader

    seconds = {topic.name: stamp_seconds(topic) for topic in topics}
    with next(source.glob("*.mcap")).open("rb") as stream:
        reader = make_reader(stream)
        messages = [(channel.topic, message.log_time, message.data)
                    for _, channel, message in reader.iter_messages(log_time_order=True)]
    with Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {t.name: writer.add_connection(t.name, t.msgtype, typestore=STORE)
                       for t in topics}
        for repetition in range(times):
            shift = repetition * shift_s
            for topic, log_ns, data in messages:
                writer.write(connections[topic], log_ns + shift * 10**9,
                             later(data, seconds[topic], shift) if shift else data)


def later(cdr: bytes, words: list[int], seconds: int) -> memoryview:
    """``cdr`` with each int32 at ``words`` (a header stamp's seconds) ``seconds`` more."""
    patched = bytearray(cdr)
    for at in words:
        STAMP_SECONDS.pack_into(patched, at, STAMP_SECONDS.unpack_from(patched, at)[0] + seconds)
    return memoryview(patched)


@dataclass(frozen=True, slots=True)
class GeneratedFile:
    """One of the issue's files in every layout asked for: layout -> its rosbag2 directory."""

    label: str
    target: float
    bags: dict[Layout, Path]


def generated_file(root: Path, label: str, topics: list[Topic], span_s: float, *,
                   layouts: Sequence[Layout], target: float) -> GeneratedFile:
    """The file's bags under ``root/label``, one directory per layout, written unless an earlier
    run finished them there (a bag's metadata.yaml is written last)."""
    wanted = [REFERENCE, *(layout for layout in layouts if layout != REFERENCE)]
    directories = {layout: root / label / layout.name for layout in wanted}
    missing = {layout: directory for layout, directory in directories.items()
               if not (directory / "metadata.yaml").exists()}
    for directory in missing.values():
        shutil.rmtree(directory, ignore_errors=True)
    written = {layout: directory for layout, directory in missing.items() if not layout.chunk_size}
    if written:
        write_bags(written, topics, int(span_s * 1e9))
    rechunked = {layout: directory for layout, directory in missing.items() if layout.chunk_size}
    if rechunked:
        rechunk_bags(directories[REFERENCE], rechunked)
    return GeneratedFile(label, target, directories)


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


@dataclass(frozen=True, slots=True)
class Figure:
    """One bag's ratio: baseline seconds / ours, the median over the rounds."""

    title: str
    ratio: float
    target: float | None

    def verdict(self) -> str:
        if self.target is None:
            return ""
        return f" (target >= {self.target}: {'met' if self.ratio >= self.target else 'MISSED'})"


@dataclass(frozen=True, slots=True)
class Timing:
    """How bags are timed: the two commands, where they write, the rounds, and the
    ``time.monotonic()`` after which a bag gets one round only, so that the script ends within
    its budget on a loaded machine (said in the output)."""

    tools: dict[str, str]
    out: Path
    rounds: int
    one_round_after: float


def compare(title: str, ours_bag: Path, baseline_bag: Path, timing: Timing, *,
            target: float | None, check_rows: bool) -> Figure:
    """Time ``rerun mcap convert baseline_bag`` against ``swanky-host --bag ours_bag``, the two
    alternating, and print the figures (and, with ``check_rows``, the rows of both .rrd files)."""
    tools, out = timing.tools, timing.out
    baseline_runs: list[float] = []
    ours_runs: list[float] = []
    for done in range(timing.rounds):
        if done and time.monotonic() > timing.one_round_after:
            break
        baseline_runs.append(timed([tools["rerun"], "mcap", "convert", str(baseline_bag),
                                    "-o", str(out / "rerun.rrd")]))
        ours_runs.append(timed([tools["swanky-host"], "--bag", str(ours_bag),
                                "--save", str(out / "swanky.rrd")]))
    rounds = len(ours_runs)
    cut = f" (of {timing.rounds}: the script's budget ran short)" if rounds < timing.rounds else ""
    baseline, ours = statistics.median(baseline_runs), statistics.median(ours_runs)
    figure = Figure(title, statistics.median(
        b / o for b, o in zip(baseline_runs, ours_runs, strict=True)), target)
    print(f"{title}")
    print(f"  baseline rerun mcap convert {baseline_bag.name}: {baseline:7.2f} s, "
          f"runs {', '.join(f'{t:.2f}' for t in baseline_runs)}")
    print(f"  swanky-host --bag {ours_bag.name} --save: {ours:7.2f} s, "
          f"runs {', '.join(f'{t:.2f}' for t in ours_runs)}")
    print(f"  ratio rerun/swanky wall time, median of {rounds}{cut}: {figure.ratio:.3f}"
          f"{figure.verdict()}", flush=True)
    if check_rows:
        compare_outputs(out / "rerun.rrd", out / "swanky.rrd")
    return figure


def compare_layouts(generated: GeneratedFile, count: int, timing: Timing,
                    check_rows: Sequence[str]) -> list[Figure]:
    """Every layout of one generated file against Rerun's importer: on the same bag where Rerun
    reads it, else on the rosbags MCAP of the same messages."""
    reference = generated.bags[REFERENCE]
    figures = []
    for layout, directory in generated.bags.items():
        files = [f for f in directory.iterdir() if f.name != "metadata.yaml"]
        size_mb = sum(f.stat().st_size for f in files) / 1e6
        baseline = next((reference if not layout.rerun_reads else directory).glob("*.mcap"))
        title = (f"{generated.label} / {layout.name}: {layout.written_by}; {count:,} messages, "
                 f"{size_mb:,.0f} MB")
        if not layout.rerun_reads:
            title += (f"\n  (rerun mcap convert reads only MCAP: its baseline is the same messages "
                      f"as the plain MCAP of {REFERENCE.name})")
        figures.append(compare(title, directory, baseline, timing, target=generated.target,
                               check_rows=layout.name in check_rows))
    return figures


def print_summary(figures: Sequence[Figure]) -> None:
    print("every ratio (rerun mcap convert seconds / swanky-host --bag --save seconds):")
    width = max(len(figure.title.split(":")[0]) for figure in figures)
    for figure in figures:
        print(f"  {figure.title.split(':')[0]:<{width}} {figure.ratio:6.3f}{figure.verdict()}")
    missed = [figure for figure in figures if figure.target is not None
              and figure.ratio < figure.target]
    print(f"targets met: {len(figures) - len(missed)} of {len(figures)}"
          + (f"; missed: {', '.join(f.title.split(':')[0] for f in missed)}" if missed else ""),
          flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bags", nargs="*", type=Path,
                        help="compare on these .mcap files instead of generating the layouts")
    parser.add_argument("--small-scale", type=float, default=1.0,
                        help="multiply the small-message file's counts (1.0: the issue's 470k)")
    parser.add_argument("--large-scale", type=float, default=1.0,
                        help="multiply the large-message file's counts (1.0: the issue's 400)")
    parser.add_argument("--rounds", type=int, default=3, help="baseline and ours, this many times")
    parser.add_argument("--tenfold-rounds", type=int, default=TENFOLD_ROUNDS,
                        help="rounds on the 10x small-message file (0: leave it out)")
    parser.add_argument("--layouts", nargs="+", default=[layout.name for layout in LAYOUTS],
                        choices=[layout.name for layout in LAYOUTS], help="these layouts only")
    parser.add_argument("--check-rows", nargs="*", default=list(CHECK_ROWS), metavar="LAYOUT",
                        help="compare both tools' rows and values on these layouts "
                             "(default %(default)s)")
    parser.add_argument("--budget", type=float, default=BUDGET_SECONDS,
                        help="seconds the script may take: past ONE_ROUND_AFTER of them, each bag "
                             "gets one round only (default %(default)s)")
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
    one_round_after = time.monotonic() + ONE_ROUND_AFTER * args.budget
    with tempfile.TemporaryDirectory(prefix="swanky_bench_") as tmp:
        out = Path(tmp)
        timing = Timing({k: str(v) for k, v in tools.items()}, out, args.rounds, one_round_after)
        if args.bags:
            for bag in args.bags:
                compare(f"{bag.name}: {message_count(bag):,} messages, "
                        f"{bag.stat().st_size / 1e6:,.0f} MB", bag, bag, timing, target=None,
                        check_rows=True)
            return 0
        layouts = [layout for layout in LAYOUTS if layout.name in args.layouts]
        root = args.keep or out
        small_label = f"small-{args.small_scale:g}"
        small_topics_ = small_topics(args.small_scale)
        files = [
            (small_label, small_topics_, SMALL_SPAN_S * args.small_scale, TARGETS["small"]),
            (f"large-{args.large_scale:g}", large_topics(args.large_scale),
             scaled(300, args.large_scale) / 30, TARGETS["large"]),  # images at 30 Hz
        ]
        figures: list[Figure] = []
        for label, topics, span_s, target in files:
            started = time.perf_counter()
            generated = generated_file(root, label, topics, span_s, layouts=layouts, target=target)
            count = sum(topic.count for topic in topics)
            print(f"{label}: {count:,} messages in {len(generated.bags)} layouts, ready in "
                  f"{time.perf_counter() - started:.1f} s", flush=True)
            figures += compare_layouts(generated, count, timing, args.check_rows)
        if args.tenfold_rounds:
            started = time.perf_counter()
            directory = root / f"small-{args.small_scale:g}x{TENFOLD}" / REFERENCE.name
            if not (directory / "metadata.yaml").exists():
                shutil.rmtree(directory, ignore_errors=True)
                write_repeated(root / small_label / REFERENCE.name, directory, small_topics_,
                               TENFOLD, math.ceil(SMALL_SPAN_S * args.small_scale))
            tenfold = GeneratedFile(f"small-{args.small_scale:g}x{TENFOLD}", TARGETS["tenfold"],
                                    {REFERENCE: directory})
            count = TENFOLD * sum(topic.count for topic in small_topics_)
            print(f"{tenfold.label}: the small file {TENFOLD} times over, {count:,} messages, "
                  f"ready in {time.perf_counter() - started:.1f} s", flush=True)
            figures += compare_layouts(
                tenfold, count, dataclasses.replace(timing, rounds=args.tenfold_rounds), ())
        print_summary(figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
